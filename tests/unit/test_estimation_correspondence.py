"""Blob correspondences: the gated assignment is global (not greedy), ambiguous pairs are left unmade, and a
third camera resolves what two cannot."""

import itertools

import numpy as np
import pytest

from services.estimation.bodies.correspondence import (
    CorrespondenceOptions,
    gated_assignment,
    triangulate_blobs,
    unambiguous,
)
from services.geometry.se3 import transform_points
from services.geometry.triangulation import reproject, triangulate
from services.synthetic import make_scene


def brute_force(cost: np.ndarray, gate: float) -> float:
    """Least total cost over every partial one-to-one matching (entries >= gate not allowed)."""
    rows, columns = cost.shape
    best = gate * (rows + columns)
    for k in range(1, min(rows, columns) + 1):
        for chosen_rows in itertools.combinations(range(rows), k):
            for chosen_columns in itertools.permutations(range(columns), k):
                entries = cost[list(chosen_rows), list(chosen_columns)]
                if np.all(entries < gate):
                    best = min(best, float(entries.sum()) + gate * (rows + columns - 2 * k))
    return best


def total(cost: np.ndarray, gate: float, matches) -> float:
    return sum(cost[r, c] for r, c in matches) + gate * (sum(cost.shape) - 2 * len(matches))


def test_assignment_is_global_where_greedy_fails():
    cost = np.array([[0.1, 0.2], [0.3, np.inf]])
    assert sorted(gated_assignment(cost, 1.0)) == [(0, 1), (1, 0)]


@pytest.mark.parametrize("seed", range(20))
def test_assignment_is_the_least_cost_partial_matching(seed):
    rng = np.random.default_rng(seed)
    cost = rng.uniform(0.0, 2.0, (rng.integers(1, 5), rng.integers(1, 5)))
    cost[rng.random(cost.shape) < 0.2] = np.inf
    matches = gated_assignment(cost, 1.0)
    assert len({r for r, _ in matches}) == len({c for _, c in matches}) == len(matches)
    assert all(cost[r, c] < 1.0 for r, c in matches)
    assert total(cost, 1.0, matches) == pytest.approx(brute_force(cost, 1.0))


def test_a_near_tie_is_left_unmade():
    tie = np.array([[0.10, 0.12], [0.11, 0.10], [np.inf, np.inf]])
    assert unambiguous(gated_assignment(tie, 1.0), tie, 1.0, 0.2) == []
    clear = np.array([[0.10, 0.90], [0.85, 0.10]])
    assert sorted(unambiguous(gated_assignment(clear, 1.0), clear, 1.0, 0.2)) == [(0, 0), (1, 1)]



@pytest.mark.parametrize("seed", range(20))
def test_kept_matches_are_those_whose_loss_costs_the_margin(seed):
    """Against brute force, on sparse tables where many blobs have one partner only (the shortcut's case)."""
    rng = np.random.default_rng(100 + seed)
    cost = rng.uniform(0.0, 1.2, (rng.integers(1, 5), rng.integers(1, 5)))
    cost[rng.random(cost.shape) < 0.6] = np.inf
    margin = float(rng.uniform(0.1, 1.5))
    matches = gated_assignment(cost, 1.0)
    expected = []
    for r, c in matches:
        without = cost.copy()
        without[r, c] = np.inf
        if brute_force(without, 1.0) - brute_force(cost, 1.0) >= margin - 1e-12:
            expected.append((r, c))
    assert sorted(unambiguous(matches, cost, 1.0, margin)) == sorted(expected)


ON_ONE_EPIPOLAR_PLANE = np.array([[-0.2, 0.0, 2.0], [0.25, 0.0, 2.4]])
"""Two points in the plane y = 0, which holds every camera centre of the bar: every camera pair
sees them on one epipolar line, so two cameras cannot tell which blob is which."""


@pytest.mark.parametrize("count", [2, 3])
def test_third_camera_resolves_an_epipolar_ambiguity(count):
    scene = make_scene("ir_rig", camera_count=count, width=1280, height=1024, baseline=1.0)
    truth = ON_ONE_EPIPOLAR_PLANE
    blobs = [reproject(c, truth) for c in scene.cameras]
    points = triangulate_blobs(scene.cameras, blobs, CorrespondenceOptions(sigma_px=0.05))
    if count == 2:
        assert points == []
    else:
        assert sorted(p.blob_indices for p in points) == [(0, 0, 0), (1, 1, 1)]
        for p in points:
            np.testing.assert_allclose(p.point, truth[p.blob_indices[0]], atol=1e-6)


def test_blobs_are_never_used_twice():
    scene = make_scene("ir_rig", camera_count=3, width=1280, height=1024, baseline=1.0)
    rng = np.random.default_rng(4)
    truth = np.concatenate([transform_points(T, scene.bodies[n]) for n, T in scene.body_poses(0).items()])
    blobs = [np.vstack([reproject(c, truth), rng.uniform((0, 0), (1280, 1024), (30, 2))]) for c in scene.cameras]
    used = [(c, i) for p in triangulate_blobs(scene.cameras, blobs) for c, i in zip(p.camera_indices, p.blob_indices,
                                                                                   strict=True)]
    assert len(used) == len(set(used)) >= 2 * len(truth)


def test_blob_lists_must_match_the_cameras():
    scene = make_scene("ir_rig", camera_count=2)
    with pytest.raises(ValueError, match="2 cameras and 1 blob lists"):
        triangulate_blobs(scene.cameras, [np.zeros((0, 2))])


@pytest.mark.parametrize("count", [2, 3])
def test_each_point_is_its_own_views_triangulated_alone(count):
    scene = make_scene("ir_rig", camera_count=count, occlusion_rate=1.0)
    rng = np.random.default_rng(count)
    made = 0
    for index in range(0, 60, 6):
        truth = np.concatenate([transform_points(T, scene.bodies[n]) for n, T in scene.body_poses(index).items()])
        blobs = [np.vstack([reproject(c, truth) + rng.normal(0.0, 0.02, (len(truth), 2)),
                            rng.uniform((0, 0), (640, 480), (3, 2))]) for c in scene.cameras]
        for point in triangulate_blobs(scene.cameras, blobs, CorrespondenceOptions(sigma_px=0.05)):
            views = [scene.cameras[c] for c in point.camera_indices]
            pixels = np.array([blobs[c][i] for c, i in zip(point.camera_indices, point.blob_indices, strict=True)])
            alone = triangulate(views, pixels, 0.05)
            np.testing.assert_allclose(point.point, alone.point, rtol=0, atol=1e-12)
            np.testing.assert_allclose(point.covariance, alone.covariance, rtol=1e-9, atol=0)
            assert point.rms_px == pytest.approx(alone.rms_px, rel=1e-9, abs=1e-12)
            made += 1
    assert made >= 10 * len(scene.bodies)


def two_spheres_each_merged_in_one_view() -> tuple[list, np.ndarray, list[np.ndarray]]:
    """Three arc cameras, spheres A and B on one epipolar plane of cameras 0 and 1: camera 0 sees A alone (B merged
    there), camera 1 sees B alone (A merged there), camera 2 both. A's blob in camera 0 and B's in camera 1 lie on
    one epipolar line: paired, they make a point 70 mm off that camera 2 sees with no blob near."""
    scene = make_scene("ir_rig", camera_count=3, layout="arc")
    cameras = scene.cameras
    centre_0, centre_1 = (np.asarray(c.T_rig_camera)[:3, 3] for c in cameras[:2])
    a = scene.body_poses(0)["tool"][:3, 3]
    b = a + 0.05 * (centre_1 - centre_0) / np.linalg.norm(centre_1 - centre_0) \
        + 0.03 * (a - centre_0) / np.linalg.norm(a - centre_0)
    truth = np.array([a, b])
    images = [reproject(c, truth) for c in cameras]
    return cameras, truth, [images[0][:1], images[1][1:], images[2]]


def test_a_pair_a_third_camera_does_not_confirm_loses_to_the_pairs_it_does_not_see():
    cameras, truth, blobs = two_spheres_each_merged_in_one_view()
    points = triangulate_blobs(cameras, blobs, CorrespondenceOptions(sigma_px=0.05))
    assert sorted((p.camera_indices, p.blob_indices) for p in points) == [((0, 2), (0, 0)), ((1, 2), (0, 1))]
    for p in points:
        np.testing.assert_allclose(p.point, truth[p.blob_indices[-1]], atol=1e-6)


def test_a_pair_no_later_camera_wants_is_still_made():
    """A sphere hidden from camera 2 (its blobs in cameras 0 and 1 alone, unconfirmed) is made once camera 2's blobs
    have gone to the spheres they are."""
    cameras, truth, blobs = two_spheres_each_merged_in_one_view()
    c = truth[0] + [0.0, 0.08, 0.0]
    hidden = [np.vstack([b, reproject(camera, c[None])]) for camera, b in zip(cameras[:2], blobs[:2], strict=True)]
    points = triangulate_blobs(cameras, [*hidden, blobs[2]], CorrespondenceOptions(sigma_px=0.05))
    assert sorted((p.camera_indices, p.blob_indices) for p in points) == [((0, 1), (1, 1)), ((0, 2), (0, 0)),
                                                                          ((1, 2), (0, 1))]
    np.testing.assert_allclose(points[[p.camera_indices for p in points].index((0, 1))].point, c, atol=1e-6)
