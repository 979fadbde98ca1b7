"""Two-view initialisation on the ``room`` scene's geometry and on degenerate motions and scenes.

Matches are exact projections of known 3D points (points spread over the room's faces, or a plane)
with 0.5 px noise and, where said, 20 % of the second frame's pixels replaced by random ones.
"""

import numpy as np
import pycolmap
import pytest

from services.geometry.camera import intrinsics, project_points
from services.geometry.rotation import matrix_from_rotvec, rotation_angle
from services.geometry.se3 import invert, make_transform, transform_points
from services.slam.initialisation import InitialisationModel, InitialisationStatus, initialise
from services.slam.two_view import fit_relative_pose, pose_std_deg, triangulate_pair
from services.synthetic import make_scene

NOISE_PX = 0.5
POINTS_PER_M2 = 400
K = intrinsics(640, 480, 64.0)


@pytest.fixture(scope="module")
def room():
    """``(scene, (M, 3) world points spread uniformly over every face of the room)``."""
    scene = make_scene("room")
    rng = np.random.default_rng(1)
    points = []
    for face in scene.faces:
        size = np.array([face.texture.width_m, face.texture.height_m])
        on_face = rng.uniform(-0.5, 0.5, (int(POINTS_PER_M2 * size.prod()), 2)) * size
        points.append(transform_points(face.T_world_face, np.column_stack([on_face, np.zeros(len(on_face))])))
    return scene, np.vstack(points)


def in_view(T_camera_world: np.ndarray, points_world: np.ndarray) -> np.ndarray:
    """(M,) whether each world point is in front of the 640x480 camera and inside its image."""
    points = transform_points(T_camera_world, points_world)
    front = points[:, 2] > 0.1
    pixels = project_points(np.where(front[:, None], points, 1.0), K)
    return front & np.all((pixels >= 0) & (pixels <= (639, 479)), axis=1)


def observe(T_first_world, T_second_world, points_world, seed, outliers=0.0, dist=None):
    """``(pixels_first, pixels_second, points in the first camera's frame, outlier mask)`` of the points
    seen by both cameras, with noise, a fraction ``outliers`` of the second frame's pixels random."""
    rng = np.random.default_rng(seed)
    seen = points_world[in_view(T_first_world, points_world) & in_view(T_second_world, points_world)]
    first = transform_points(T_first_world, seen)
    second = transform_points(T_second_world, seen)
    pixels = [project_points(p, K, dist) + rng.normal(0.0, NOISE_PX, (len(p), 2)) for p in (first, second)]
    wrong = rng.random(len(seen)) < outliers
    pixels[1][wrong] = rng.uniform((0, 0), (640, 480), (wrong.sum(), 2))
    return pixels[0], pixels[1], first, wrong


def pose_errors_deg(T_estimated: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    """(rotation error, angle between the translation directions), degrees."""
    direction = T_true[:3, 3] / np.linalg.norm(T_true[:3, 3])
    angle = np.arccos(np.clip(T_estimated[:3, 3] @ direction, -1.0, 1.0))
    return np.degrees(rotation_angle(T_estimated[:3, :3], T_true[:3, :3])), float(np.degrees(angle))


@pytest.mark.parametrize(("first", "second"), [(0, 45), (100, 130), (100, 145)])
def test_room_frames_far_enough_apart_initialise(room, first, second):
    scene, points_world = room
    T_first_world, T_second_world = (invert(scene.camera_pose(i)) for i in (first, second))
    pixels_first, pixels_second, truth, wrong = observe(T_first_world, T_second_world, points_world, first, 0.2)
    result = initialise(pixels_first, pixels_second, K, np.zeros(5))

    assert result.status is InitialisationStatus.INITIALISED and result.initialised
    assert result.model is InitialisationModel.ESSENTIAL
    T = result.T_second_first
    assert T is not None and np.linalg.norm(T[:3, 3]) == pytest.approx(1.0)
    rotation_deg, direction_deg = pose_errors_deg(T, T_second_world @ invert(T_first_world))
    assert rotation_deg < 0.5 and direction_deg < 3.0
    assert result.parallax_deg > 3.0 and result.in_front > 0.99

    kept = result.inliers
    assert kept.sum() > 0.9 * (~wrong).sum() and (kept & wrong).sum() < 0.01 * kept.sum()
    assert np.all(np.isnan(result.points[~kept])) and np.all(np.isfinite(result.points[kept]))
    points = result.points[kept]
    for pixels, T_camera_first in ((pixels_first, np.eye(4)), (pixels_second, T)):
        error = np.linalg.norm(project_points(transform_points(T_camera_first, points), K) - pixels[kept], axis=1)
        assert np.median(error) < 1.0 and error.max() < 3.0
    scale = np.sum(points * truth[kept]) / np.sum(points * points)
    residual = np.linalg.norm(scale * points - truth[kept], axis=1) / np.linalg.norm(truth[kept], axis=1)
    print(f"\nframes {first}/{second}: {len(pixels_first)} matches, rotation {rotation_deg:.2f} deg, direction "
          f"{direction_deg:.2f} deg, parallax {result.parallax_deg:.1f} deg, points {100 * np.median(residual):.1f} %")
    assert np.median(residual) < 0.03
    assert scale == pytest.approx(np.linalg.norm(scene.camera_pose(second)[:3, 3] - scene.camera_pose(first)[:3, 3]),
                                  rel=0.03)


def test_distortion_is_undone_first(room):
    scene, points_world = room
    dist = np.array([-0.25, 0.08, 0.001, -0.001, 0.0])
    T_first_world, T_second_world = (invert(scene.camera_pose(i)) for i in (0, 45))
    pixels_first, pixels_second, _, _ = observe(T_first_world, T_second_world, points_world, 7, dist=dist)
    result = initialise(pixels_first, pixels_second, K, dist)
    assert result.initialised and result.T_second_first is not None
    rotation_deg, direction_deg = pose_errors_deg(result.T_second_first, T_second_world @ invert(T_first_world))
    assert rotation_deg < 0.3 and direction_deg < 2.0


@pytest.mark.parametrize(("first", "second"), [(300, 345), (500, 545)])
def test_room_frames_facing_a_wall_initialise_right_or_wait(room, first, second):
    """The camera faces a wall 2.6-3.1 m away (10 % depth range): across sixteen draws of noise and
    outliers, a pose is given only when it is right; the others wait for the pose to be determined."""
    scene, points_world = room
    T_first_world, T_second_world = (invert(scene.camera_pose(i)) for i in (first, second))
    T_true = T_second_world @ invert(T_first_world)
    errors, waiting = [], []
    for seed in range(16):
        pixels_first, pixels_second, _, _ = observe(T_first_world, T_second_world, points_world, seed, 0.2)
        result = initialise(pixels_first, pixels_second, K, np.zeros(5))
        if result.initialised:
            assert result.T_second_first is not None
            errors.append(pose_errors_deg(result.T_second_first, T_true))
        else:
            assert result.status is InitialisationStatus.POSE_UNCERTAIN and not result.inliers.any()
            waiting.append(result.pose_std_deg)
    print(f"\nframes {first}/{second}: {len(errors)} initialised, worst rotation "
          f"{max((e[0] for e in errors), default=float('nan')):.2f} deg, direction "
          f"{max((e[1] for e in errors), default=float('nan')):.2f} deg; {len(waiting)} pose_uncertain")
    assert all(rotation < 1.0 and direction < 5.0 for rotation, direction in errors)
    assert all(rotation > 0.5 for rotation, _ in waiting)
    assert len(errors) >= (0 if first == 300 else 14)


def test_predicted_pose_spread_matches_the_spread_of_refined_poses(room):
    """``pose_std_deg`` against Monte Carlo: the same matches with fresh noise, each pose refined from
    the truth by pycolmap's Sampson refinement; the RMS errors agree with the prediction within 30 %."""
    scene, points_world = room
    T_first_world, T_second_world = (invert(scene.camera_pose(i)) for i in (500, 545))
    T_true = T_second_world @ invert(T_first_world)
    T_unit = make_transform(T_true[:3, :3], T_true[:3, 3] / np.linalg.norm(T_true[:3, 3]))
    camera = pycolmap.Camera(model="PINHOLE", width=640, height=480, params=[K[0, 0], K[1, 1], K[0, 2], K[1, 2]])
    errors = []
    for seed in range(40):
        pixels_first, pixels_second, _, _ = observe(T_first_world, T_second_world, points_world, seed)
        refined = pycolmap.refine_relative_pose(pycolmap.Rigid3d(T_unit[:3]), camera, pixels_first, camera,
                                                pixels_second, np.ones(len(pixels_first), bool))
        matrix = refined["cam2_from_cam1"].matrix()
        errors.append(pose_errors_deg(make_transform(matrix[:, :3], matrix[:, 3] / np.linalg.norm(matrix[:, 3])),
                                      T_true))
    measured = np.sqrt(np.mean(np.square(errors), axis=0))
    predicted = pose_std_deg(T_unit, K, pixels_first, pixels_second, NOISE_PX)
    print(f"\npredicted {predicted[0]:.3f} / {predicted[1]:.3f} deg, "
          f"measured {measured[0]:.3f} / {measured[1]:.3f} deg")
    assert measured == pytest.approx(predicted, rel=0.3)


@pytest.mark.parametrize("axis", [(0.0, 1.0, 0.0), (1.0, 0.0, 0.0), (0.3, 0.8, 0.5)])
def test_pure_rotation_waits_for_parallax(room, axis):
    scene, points_world = room
    T_first_world = invert(scene.camera_pose(200))
    rotation = make_transform(matrix_from_rotvec(np.radians(8.0) * np.array(axis) / np.linalg.norm(axis)), np.zeros(3))
    pixels_first, pixels_second, _, _ = observe(T_first_world, rotation @ T_first_world, points_world, 3, 0.2)
    result = initialise(pixels_first, pixels_second, K, np.zeros(5))
    assert result.status is InitialisationStatus.LOW_PARALLAX and not result.initialised
    assert result.parallax_deg < 0.5
    assert not result.inliers.any() and np.all(np.isnan(result.points))


def test_room_frames_too_close_wait_for_parallax(room):
    scene, points_world = room
    T_first_world, T_second_world = (invert(scene.camera_pose(i)) for i in (0, 2))
    pixels_first, pixels_second, _, _ = observe(T_first_world, T_second_world, points_world, 5, 0.2)
    assert initialise(pixels_first, pixels_second, K, np.zeros(5)).status is InitialisationStatus.LOW_PARALLAX


def full_fit_parallax_deg(pixels_first: np.ndarray, pixels_second: np.ndarray) -> float:
    """The median parallax the full fit measures: pycolmap's refined pose, its inliers triangulated, the
    angle at each point between its directions to the two camera centres."""
    T, inliers = fit_relative_pose(pixels_first, pixels_second, K, 1.0, 0.999)
    assert T is not None
    points = triangulate_pair(K, T, pixels_first[inliers], pixels_second[inliers]).points
    to_first, to_second = -points, -T[:3, :3].T @ T[:3, 3] - points
    cos = np.sum(to_first * to_second, axis=1) / np.linalg.norm(to_first, axis=1) / np.linalg.norm(to_second, axis=1)
    return float(np.degrees(np.arccos(np.clip(np.median(cos), -1.0, 1.0))))


@pytest.mark.parametrize("pair", ["rotation", "frames 0 / 2", "frames 0 / 3"])
def test_low_parallax_is_told_before_the_full_fit_as_the_full_fit_tells_it(room, pair):
    """Pairs whose parallax is well under the bound end in ``low_parallax`` from the fits' own poses, before
    pycolmap's pose, the triangulation and the pose's spread (none of them measured: NaN spread, no
    point in front), the status the full fit gives them: its median parallax is under the bound too."""
    scene, points_world = room
    T_first_world = invert(scene.camera_pose(0))
    if pair == "rotation":
        T_second_world = make_transform(matrix_from_rotvec([0.0, 0.1, 0.02]), np.zeros(3)) @ T_first_world
    else:
        T_second_world = invert(scene.camera_pose(int(pair[-1])))
    pixels_first, pixels_second, _, _ = observe(T_first_world, T_second_world, points_world, 4, 0.2)
    result = initialise(pixels_first, pixels_second, K, np.zeros(5))
    assert result.status is InitialisationStatus.LOW_PARALLAX
    assert np.isnan(result.pose_std_deg[0]) and result.in_front == 0.0
    assert result.parallax_deg < 1.0 and full_fit_parallax_deg(pixels_first, pixels_second) < 1.0


@pytest.mark.parametrize("seed", range(6))
def test_a_plane_is_initialised_from_its_homography_or_waited_out(seed):
    """Points on one plane 3 m away: the homography is the model; a pose is given only when its
    decompositions can be told apart, and it is then right."""
    rng = np.random.default_rng(seed)
    T_first_plane = make_transform(matrix_from_rotvec([rng.uniform(-0.5, 0.5), rng.uniform(-0.3, 0.3), 0.0]),
                                   [0.0, 0.0, 3.0])
    on_plane = np.column_stack([rng.uniform(-2.0, 2.0, (600, 2)), np.zeros(600)])
    baseline = rng.normal(0.0, 1.0, 3)
    T_second_first = make_transform(matrix_from_rotvec(rng.normal(0.0, 0.08, 3)),
                                    0.4 * baseline / np.linalg.norm(baseline))
    pixels_first, pixels_second, _, _ = observe(T_first_plane, T_second_first @ T_first_plane, on_plane, seed)
    result = initialise(pixels_first, pixels_second, K, np.zeros(5))
    assert result.model is InitialisationModel.HOMOGRAPHY
    assert result.status in (InitialisationStatus.INITIALISED, InitialisationStatus.PLANAR_WAIT)
    if result.initialised:
        assert result.T_second_first is not None
        rotation_deg, direction_deg = pose_errors_deg(result.T_second_first, T_second_first)
        assert rotation_deg < 0.3 and direction_deg < 2.0
    else:
        assert not result.inliers.any()


def test_too_few_matches(room):
    scene, points_world = room
    T_first_world, T_second_world = (invert(scene.camera_pose(i)) for i in (0, 45))
    pixels_first, pixels_second, _, _ = observe(T_first_world, T_second_world, points_world, 0)
    result = initialise(pixels_first[:40], pixels_second[:40], K, np.zeros(5))
    assert result.status is InitialisationStatus.TOO_FEW_MATCHES and result.T_second_first is None
    assert result.inliers.shape == (40,) and result.points.shape == (40, 3)


def test_random_matches_do_not_initialise():
    rng = np.random.default_rng(0)
    pixels_first, pixels_second = (rng.uniform((0, 0), (640, 480), (300, 2)) for _ in range(2))
    assert not initialise(pixels_first, pixels_second, K, np.zeros(5)).initialised


PLANE_MOTIONS = [((0.0, 0.3, 1.0), (0.5, 0.0, 1.0)), ((0.3, 0.3, 1.0), (0.7, 0.7, 0.3)),
                 ((0.2, 1.0, 0.3), (0.8, 0.3, 0.7))]


@pytest.mark.parametrize(("first_motion", "second_motion"), PLANE_MOTIONS)
def test_a_later_pair_with_the_same_first_frame_tells_the_planes_decompositions_apart(first_motion, second_motion):
    """A wall 3 m away, the camera moving 0.3 m one way, then 0.4 m another: each pair alone leaves the
    homography's two decompositions ambiguous (``planar_wait``). Given the first pair's normals, the second
    pair keeps the one whose normal did not move, and its pose is right; normals that neither pair has
    tell nothing apart."""
    T_first_plane = make_transform(matrix_from_rotvec([0.15, -0.2, 0.0]), [0.0, 0.0, 3.0])
    rng = np.random.default_rng(3)
    on_plane = np.column_stack([rng.uniform(-2.0, 2.0, (600, 2)), np.zeros(600)])
    poses = []
    for direction, length in ((first_motion, 0.3), (second_motion, 0.4)):
        unit = np.array(direction) / np.linalg.norm(direction)
        poses.append(make_transform(matrix_from_rotvec([0.0, 0.02, 0.0]), -length * unit))
    pairs = [observe(T_first_plane, T @ T_first_plane, on_plane, 5)[:2] for T in poses]
    alone = [initialise(*pair, K, np.zeros(5)) for pair in pairs]
    assert [result.status for result in alone] == [InitialisationStatus.PLANAR_WAIT] * 2
    assert alone[0].plane_normals.shape == (2, 3)

    told = initialise(*pairs[1], K, np.zeros(5), planes=alone[0].plane_normals)
    assert told.initialised and told.T_second_first is not None
    rotation_deg, direction_deg = pose_errors_deg(told.T_second_first, poses[1])
    assert rotation_deg < 0.3 and direction_deg < 2.0
    true_normal = T_first_plane[:3, 2]
    assert min(np.degrees(np.arccos(abs(n @ true_normal))) for n in alone[0].plane_normals) < 3.0

    elsewhere = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    assert initialise(*pairs[1], K, np.zeros(5), planes=elsewhere).status is InitialisationStatus.PLANAR_WAIT
