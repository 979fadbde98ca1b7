"""Bodies followed in the images: the same points and poses as the full path where it sees the same views, and
the body kept through a sphere hidden in a view, a stray near it, two spheres merged (in one view, or in every view
with the blob split), a split blob's part off its sphere, and a decoy of it."""

import numpy as np
import pytest

from services.estimation.bodies.correspondence import CorrespondenceOptions, triangulate_blobs
from services.estimation.bodies.labelled import label_parts, track_blobs
from services.estimation.bodies.node import BodiesPerSet, Params, pixels, point_arrays
from services.estimation.bodies.rigid import MatchOptions, match_bodies
from services.estimation.bodies.tracking import TrackingOptions
from services.geometry.evaluation import pose_error
from services.geometry.rotation import matrix_from_rotvec
from services.geometry.se3 import make_transform, transform_points
from services.geometry.triangulation import reproject
from services.synthetic import make_scene
from services.synthetic.ir_rig import LAYOUTS
from tests.ir_tracking import rendered_blobs

SIGMA_PX = 0.012
NOISE_PX = 0.02
CORRESPONDENCE = CorrespondenceOptions(sigma_px=SIGMA_PX)
SLIGHTLY_OFF = make_transform(matrix_from_rotvec(np.array([0.002, -0.001, 0.001])), np.array([0.0005, -0.0003, 0.0004]))
"""A prediction's error: 0.7 mm and 0.14 deg, about what one instant at 30 Hz leaves (well under a pixel)."""


def views_of(found, match) -> list[tuple[tuple[int, ...], tuple[int, ...]]]:
    return sorted((found.points[k].camera_indices, found.points[k].blob_indices) for k in match.indices if k >= 0)


def test_the_predicted_path_gives_the_full_paths_points_and_poses_where_it_sees_the_same_views():
    scene = make_scene("ir_rig")
    indices = range(30)
    frames = rendered_blobs(scene, indices)
    names = tuple(c.name for c in scene.cameras)
    full = BodiesPerSet(scene.bodies, Params(cameras=names, predict=False, sigma_px=SIGMA_PX))
    followed = BodiesPerSet(scene.bodies, Params(cameras=names, sigma_px=SIGMA_PX))
    compared = 0
    for index, frame in zip(indices, frames, strict=True):
        blobs = [pixels(b, flagged=False) for b in frame]
        stamp_ns = round(scene.time_s(index) * 1e9)
        before, _ = full(stamp_ns, list(scene.cameras), blobs)
        after, _ = followed(stamp_ns, list(scene.cameras), blobs)
        assert set(before.matching.bodies) <= set(after.matching.bodies), index
        truth = scene.body_poses(index)
        for name, match in after.matching.bodies.items():
            assert pose_error(match.fit.T_world_body, truth[name])[1] < 0.002, (index, name)  # never a ghost
            if name not in before.matching.bodies:
                continue
            if views_of(before, before.matching.bodies[name]) != views_of(after, match):
                continue
            old = before.matching.bodies[name]
            np.testing.assert_allclose(match.fit.T_world_body, old.fit.T_world_body, rtol=0, atol=1e-9)
            scale = np.max(np.abs(old.fit.covariance))  # the points agree to 1e-10 m, started from other places
            np.testing.assert_allclose(match.fit.covariance, old.fit.covariance, rtol=1e-9, atol=1e-9 * scale)
            assert match.fit.residual_rms == pytest.approx(old.fit.residual_rms, rel=1e-9, abs=1e-9)  # m, as the points
            pairs = {(p.camera_indices, p.blob_indices): p for p in before.points}
            for k in match.indices[match.indices >= 0]:
                point = after.points[k]
                same = pairs[(point.camera_indices, point.blob_indices)]
                np.testing.assert_allclose(point.point, same.point, rtol=0, atol=1e-9)
                np.testing.assert_allclose(point.covariance, same.covariance, rtol=1e-9, atol=0)
                assert point.rms_px == pytest.approx(same.rms_px, rel=1e-9, abs=1e-12)
            compared += 1
    # Of 90 body-instants: the head with two spheres merged in one view is kept by both paths (the full one finds it
    # from its three other spheres), where they see the same views with the same points and pose.
    assert compared >= 80


def seen(scene, poses, hidden=frozenset(), rng=None):
    """Blobs of the bodies' spheres at ``poses`` in every camera (less ``hidden``: (camera, body, sphere)), with
    centroid noise, and per camera the blob index of each (body, sphere)."""
    rng = rng or np.random.default_rng(0)
    blobs, where = [], []
    for c, camera in enumerate(scene.cameras):
        rows, index = [], {}
        for name, T in poses.items():
            for j, pixel in enumerate(reproject(camera, transform_points(T, scene.bodies[name]))):
                if (c, name, j) not in hidden:
                    index[(name, j)] = len(rows)
                    rows.append(pixel + rng.normal(0.0, NOISE_PX, 2))
        blobs.append(np.array(rows).reshape(-1, 2))
        where.append(index)
    return blobs, where


def follow(scene, blobs, predictions):
    return track_blobs(scene.cameras, blobs, scene.bodies, predictions, point_arrays, CORRESPONDENCE,
                       MatchOptions(), TrackingOptions())


@pytest.mark.parametrize("count", [2, 3])
def test_a_sphere_hidden_in_one_camera_is_triangulated_from_the_others(count):
    scene = make_scene("ir_rig", camera_count=count, baseline=0.8 if count == 3 else 0.3)
    poses = scene.body_poses(40)
    blobs, _ = seen(scene, poses, frozenset({(1, "tool", 0)}))
    found = follow(scene, blobs, {name: T @ SLIGHTLY_OFF for name, T in poses.items()})
    tool = found.matching.bodies["tool"]
    assert tool.spheres_used == (4 if count == 3 else 3)
    assert (tool.indices[0] >= 0) == (count == 3)
    if count == 3:
        assert found.points[tool.indices[0]].camera_indices == (0, 2)
    assert pose_error(tool.fit.T_world_body, poses["tool"])[1] < (0.0005 if count == 3 else 0.0015)
    assert set(found.matching.bodies) == set(scene.bodies)


def test_a_stray_near_a_sphere_and_one_far_away_are_never_labelled():
    scene = make_scene("ir_rig")
    poses = scene.body_poses(40)
    predictions = {name: T @ SLIGHTLY_OFF for name, T in poses.items()}
    blobs, where = seen(scene, poses)
    clean = follow(scene, blobs, predictions)
    sphere = blobs[0][where[0][("tool", 2)]]
    strays = [np.vstack([b, sphere + (4.0, 3.0), (20.0, 30.0)]) if c == 0 else b for c, b in enumerate(blobs)]
    found = follow(scene, strays, predictions)
    for name, match in clean.matching.bodies.items():
        again = found.matching.bodies[name]
        assert np.array_equal(match.indices, again.indices)
        np.testing.assert_array_equal(again.fit.T_world_body, match.fit.T_world_body)
    labelled = {i for p in found.points for c, i in zip(p.camera_indices, p.blob_indices, strict=True) if c == 0}
    assert not labelled & {len(blobs[0]), len(blobs[0]) + 1}


def merging_pose(scene, body: str, first: int, second: int, apart_px: float) -> np.ndarray:
    """A ``T_world_body`` about 2.2 m ahead whose spheres ``first`` and ``second`` lie nearly on one ray of cam0:
    their images ``apart_px`` apart."""
    spheres = scene.bodies[body]
    camera = scene.cameras[0]
    centre = camera.T_rig_camera[:3, 3]
    middle = np.array([0.05, 0.02, 2.2])
    ray = (middle - centre) / np.linalg.norm(middle - centre)
    along = spheres[second] - spheres[first]
    axis = np.cross(along / np.linalg.norm(along), ray)
    angle = np.arcsin(np.linalg.norm(axis))
    if along @ ray < 0:
        angle = np.pi - angle
    R = matrix_from_rotvec(axis / np.linalg.norm(axis) * angle)
    sideways = np.cross(ray, [0.0, 1.0, 0.0])
    R = matrix_from_rotvec(sideways / np.linalg.norm(sideways) * apart_px / camera.K[0, 0] * 2.2
                           / np.linalg.norm(along)) @ R
    return make_transform(R, middle - R @ (spheres[first] + spheres[second]) / 2)


@pytest.mark.parametrize("count", [2, 3])
def test_two_spheres_merged_in_one_view_lose_that_view_only(count):
    scene = make_scene("ir_rig", camera_count=count, baseline=0.8 if count == 3 else 0.3, body_count=3)
    poses = {"head": merging_pose(scene, "head", 0, 3, 2.0)}  # its farthest two, 175 mm apart
    blobs, where = seen(scene, poses)
    a, b = where[0][("head", 0)], where[0][("head", 3)]
    assert 1.0 < np.linalg.norm(blobs[0][a] - blobs[0][b]) < 3.0
    merged = np.mean(blobs[0][[a, b]], axis=0)
    blobs[0] = np.vstack([np.delete(blobs[0], [a, b], axis=0), merged])
    found = follow(scene, blobs, {"head": poses["head"] @ SLIGHTLY_OFF})
    head = found.matching.bodies["head"]
    assert head.spheres_used == (5 if count == 3 else 3)
    assert all(found.points[k].camera_indices == (1, 2) for k in head.indices[[0, 3]] if k >= 0)
    assert pose_error(head.fit.T_world_body, poses["head"])[1] < (0.0005 if count == 3 else 0.0015)
    merged_index = len(blobs[0]) - 1
    assert not any(0 in p.camera_indices and p.blob_indices[0] == merged_index
                   for p in found.points[:sum(m.spheres_used for m in found.matching.bodies.values())])


def test_a_decoy_repeating_a_body_away_from_its_prediction_is_not_taken():
    """The tool lacks a sphere in one camera (three spheres seen by both); a decoy of all four of its spheres lies
    elsewhere. By distances alone the decoy is the better tool; followed, the tool is where it is predicted."""
    scene = make_scene("ir_rig", body_count=2)
    poses = scene.body_poses(40)
    decoy = make_transform(matrix_from_rotvec(np.array([0.4, -1.1, 0.3])), np.array([-0.3, 0.25, 2.5]))
    blobs, _ = seen(scene, {"tool": poses["tool"]}, frozenset({(1, "tool", 3)}))
    decoy_blobs, _ = seen(scene, {"tool": decoy}, rng=np.random.default_rng(1))
    blobs = [np.vstack([b, d]) for b, d in zip(blobs, decoy_blobs, strict=True)]
    bodies = {"tool": LAYOUTS["tool"]}
    searched = match_bodies(bodies, *point_arrays(triangulate_blobs(scene.cameras, blobs, CORRESPONDENCE)))
    assert pose_error(searched.bodies["tool"].fit.T_world_body, decoy)[1] < 0.001  # the ghost the search takes
    found = track_blobs(scene.cameras, blobs, bodies, {"tool": poses["tool"] @ SLIGHTLY_OFF}, point_arrays,
                        CORRESPONDENCE, MatchOptions(), TrackingOptions())
    tool = found.matching.bodies["tool"]
    assert tool.spheres_used == 3 and pose_error(tool.fit.T_world_body, poses["tool"])[1] < 0.0015
    assert len(found.matching.unassigned) == len(found.points) - 3 >= 4  # the decoy's points: published, unlabelled


def merged_everywhere(scene, poses, body, first, second, shift_px=(0.0, 0.0)):
    """``seen`` with spheres ``first`` and ``second`` of ``body`` one blob in every camera (their mean, left out as
    flagged blobs are) and their pixels as the two parts of that blob, the first part moved by ``shift_px`` in
    cam0; the blobs, the parts per camera and the parts' indices in the labelled views."""
    blobs, where = seen(scene, poses)
    parts, indices = [], []
    for c, index in enumerate(where):
        a, b = index[(body, first)], index[(body, second)]
        pair = blobs[c][[a, b]] + (np.array([shift_px, (0.0, 0.0)]) if c == 0 else 0.0)
        blobs[c] = np.delete(blobs[c], [a, b], axis=0)
        parts.append(pair[None])
        indices.append((len(blobs[c]), len(blobs[c]) + 1))
    return blobs, parts, indices


@pytest.mark.parametrize("count", [2, 3])
def test_two_spheres_merged_in_every_view_are_triangulated_from_the_split_blobs_parts(count):
    scene = make_scene("ir_rig", camera_count=count, baseline=0.8 if count == 3 else 0.3, body_count=3)
    poses = {"head": merging_pose(scene, "head", 0, 3, 4.0)}
    blobs, parts, indices = merged_everywhere(scene, poses, "head", 0, 3)
    prediction = {"head": poses["head"] @ SLIGHTLY_OFF}
    without = follow(scene, blobs, prediction).matching.bodies["head"]
    assert without.spheres_used == 3
    found = track_blobs(scene.cameras, blobs, scene.bodies, prediction, point_arrays, CORRESPONDENCE, MatchOptions(),
                        TrackingOptions(), parts)
    head = found.matching.bodies["head"]
    assert head.spheres_used == 5
    for sphere in (0, 3):
        point = found.points[head.indices[sphere]]
        assert point.camera_indices == tuple(range(count))
        assert point.blob_indices == tuple(pair[0 if sphere == 0 else 1] for pair in indices)
    assert pose_error(head.fit.T_world_body, poses["head"])[1] < pose_error(without.fit.T_world_body,
                                                                              poses["head"])[1]


@pytest.mark.parametrize("count", [2, 3])
def test_a_part_off_its_sphere_is_dropped_not_taken(count):
    """A part 2.6 px off its sphere's image in cam0 (within the labelling gate): the view is dropped by its residual
    (the sphere made from the other two cameras) or the sphere let go by the fit, never taken."""
    scene = make_scene("ir_rig", camera_count=count, baseline=0.8 if count == 3 else 0.3, body_count=3)
    poses = {"head": merging_pose(scene, "head", 0, 3, 4.0)}
    blobs, parts, _ = merged_everywhere(scene, poses, "head", 0, 3, shift_px=(2.6, 0.0))
    found = track_blobs(scene.cameras, blobs, scene.bodies, {"head": poses["head"] @ SLIGHTLY_OFF}, point_arrays,
                        CORRESPONDENCE, MatchOptions(), TrackingOptions(), parts)
    head = found.matching.bodies["head"]
    assert head.spheres_used >= 4
    assert head.indices[0] < 0 or found.points[head.indices[0]].camera_indices == (1, 2)
    assert pose_error(head.fit.T_world_body, poses["head"])[1] < (0.0005 if count == 3 else 0.0015)


def test_a_split_blobs_parts_go_only_to_exactly_two_predicted_spheres_inside_it():
    projected = np.array([[[10.0, 10.0]], [[14.0, 10.0]], [[40.0, 40.0]]])
    parts = [np.array([[[14.2, 10.1], [10.1, 9.9]]])]
    blobs = [np.array([[40.0, 40.1]])]
    unlabelled = np.array([[-1], [-1], [0]])
    labels, observed = label_parts(projected, blobs, parts, unlabelled, 3.0)
    assert labels[:, 0].tolist() == [2, 1, 0]
    np.testing.assert_array_equal(observed[0], [[40.0, 40.1], [14.2, 10.1], [10.1, 9.9]])
    crowded = np.array([[[10.0, 10.0]], [[14.0, 10.0]], [[12.0, 11.0]]])
    assert label_parts(crowded, blobs, parts, np.full((3, 1), -1), 3.0)[0].tolist() == [[-1], [-1], [-1]]
    alone = label_parts(projected[[0, 2]], blobs, parts, np.array([[-1], [0]]), 3.0)[0]
    assert alone.tolist() == [[-1], [0]]
    taken = label_parts(projected, blobs, parts, np.array([[-1], [0], [-1]]), 3.0)[0]
    assert taken.tolist() == [[-1], [0], [-1]]


def test_a_set_found_before_its_fits_are_learnt_is_the_set_of_a_whole_step():
    """The node publishes a set's poses (``find``) before it takes the fits into the motions (``learn``): the sets
    are those of ``__call__``, and ``find`` alone leaves every motion as it was."""
    scene = make_scene("ir_rig")
    indices = range(12)
    names = tuple(c.name for c in scene.cameras)
    whole = BodiesPerSet(scene.bodies, Params(cameras=names, sigma_px=SIGMA_PX))
    split = BodiesPerSet(scene.bodies, Params(cameras=names, sigma_px=SIGMA_PX))
    for index, frame in zip(indices, rendered_blobs(scene, indices), strict=True):
        blobs = [pixels(b, flagged=False) for b in frame]
        stamp_ns = round(scene.time_s(index) * 1e9)
        expected, expected_bridged = whole(stamp_ns, list(scene.cameras), blobs)
        velocities = {name: model.velocity() if model.ready else None for name, model in split.tracker.models.items()}
        found, bridged = split.find(stamp_ns, list(scene.cameras), blobs)
        for name, model in split.tracker.models.items():
            assert (model.velocity() if model.ready else None) is velocities[name]  # nothing learnt yet
        split.learn(stamp_ns, found)
        assert set(found.matching.bodies) == set(expected.matching.bodies) and bridged.keys() == expected_bridged.keys()
        for name, match in found.matching.bodies.items():
            np.testing.assert_array_equal(match.fit.T_world_body, expected.matching.bodies[name].fit.T_world_body)
    assert all(model.ready for model in split.tracker.models.values())
