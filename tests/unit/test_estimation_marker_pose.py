"""Marker pose estimator: exact poses by every method, distortion, failures counted by reason,
the planar ambiguity resolved by the anchored track, and marker maps (planar and not)."""

from typing import Any

import numpy as np
import pytest

from services.estimation.markers.map import MapMarker, MarkerMap, map_from_poses, marker_corners
from services.estimation.markers.pose import METHODS, MarkerPoseEstimator, MarkerPoseOptions, single_observation
from services.geometry.camera import intrinsics, project_points
from services.geometry.planar_pnp import ippe_candidates
from services.geometry.rotation import matrix_from_rotvec, rotation_angle
from services.geometry.se3 import invert, make_transform, transform_points
from services.synthetic import make_scene

K = intrinsics(640, 480, 56.0)
L = 0.05


def make_estimator(marker_map: MarkerMap | None = None, **options: Any) -> MarkerPoseEstimator:
    """An estimator with ``options`` (``MarkerPoseOptions`` fields)."""
    return MarkerPoseEstimator(MarkerPoseOptions(**options), marker_map)


def corners_of(T_cam_marker: np.ndarray, length: float = L, dist: np.ndarray | None = None) -> np.ndarray:
    return project_points(transform_points(T_cam_marker, marker_corners(length)), K, dist)


def pose(rotvec, t) -> np.ndarray:
    """``T_cam_marker`` of a marker facing the camera (its z towards it), turned by ``rotvec`` and at ``t``."""
    return make_transform(matrix_from_rotvec(rotvec) @ np.diag([1.0, -1.0, -1.0]), t)


POSES = [pose([0.3, -0.2, 0.1], [0.02, -0.01, 0.4]), pose([-0.6, 0.4, 2.0], [-0.05, 0.03, 0.6]),
         pose([0.1, 0.9, -0.4], [0.0, 0.0, 0.25])]


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("T", POSES)
def test_every_method_recovers_an_exact_pose(method, T):
    result = make_estimator(method=method).estimate([7], corners_of(T)[None], [L], K)
    assert not result.failures
    (found,) = result.poses
    assert found.target == "marker/7" and found.marker_ids == (7,) and found.points == 4
    assert np.allclose(found.T, T, atol=1e-7)
    assert found.rms_px < 1e-6 and not found.ambiguous
    assert found.covariance.shape == (6, 6) and np.allclose(found.covariance, found.covariance.T)
    assert np.all(np.linalg.eigvalsh(found.covariance) > 0)


def test_distorted_corners_are_undistorted_first():
    dist = np.array([-0.25, 0.08, 0.001, -0.002, 0.0])
    T = pose([0.2, 0.3, 0.0], [0.12, 0.08, 0.5])
    corners = corners_of(T, dist=dist)[None]
    with_dist = MarkerPoseEstimator().estimate([1], corners, [L], K, dist).poses[0]
    without = MarkerPoseEstimator().estimate([1], corners, [L], K).poses[0]
    assert np.allclose(with_dist.T, T, atol=1e-6)
    assert np.linalg.norm(without.T[:3, 3] - T[:3, 3]) > 1e-3


@pytest.mark.parametrize(("name", "corners"), [
    ("collinear", [[100, 100], [150, 100], [200, 100], [250, 100]]),
    ("coincident", [[100, 100]] * 4),
    ("zero_area", [[100, 100], [150, 100], [100, 100], [150, 100]]),
    ("three_collinear", [[100, 100], [150, 100], [200, 100], [150, 150]]),
    ("not_finite", [[100, 100], [150, np.nan], [150, 150], [100, 150]]),
    ("mirrored", [[100, 100], [100, 150], [150, 150], [150, 100]]),
    ("bow_tie", [[100, 100], [150, 100], [100, 150], [150, 150]]),
])
@pytest.mark.parametrize("method", METHODS)
def test_degenerate_corners_give_no_pose_and_a_reason(name, corners, method):
    good = corners_of(POSES[0])
    result = make_estimator(method=method).estimate([1, 2], np.array([corners, good], dtype=float), L, K)
    assert [p.target for p in result.poses] == ["marker/2"]
    assert result.failures == {"degenerate_corners": 1}


def test_missing_side_lengths_and_duplicate_ids_are_counted():
    corners = np.array([corners_of(T) for T in POSES])
    result = MarkerPoseEstimator().estimate([4, 4, 5], corners, [L, L, 0.0], K)
    assert result.poses == [] and result.failures == {"duplicate_id": 2, "no_side_length": 1}
    result = MarkerPoseEstimator().estimate([1, 2, 3], corners, [np.nan, -1.0, L], K)
    assert [p.target for p in result.poses] == ["marker/3"] and result.failures == {"no_side_length": 2}


def test_an_empty_frame_gives_nothing():
    result = MarkerPoseEstimator().estimate([], np.zeros((0, 4, 2)), [], K)
    assert result.poses == [] and not result.failures


def test_bad_arguments_are_refused():
    with pytest.raises(ValueError, match="method"):
        make_estimator(method="pnp")
    with pytest.raises(ValueError, match=r"K must have shape \(3, 3\), got \(4, 4\)"):
        MarkerPoseEstimator().estimate([1], corners_of(POSES[0])[None], L, np.eye(4))


def test_covariance_follows_the_corner_sigma():
    corners = corners_of(POSES[1])[None]
    half = make_estimator(corner_sigma_px=0.5).estimate([1], corners, L, K).poses[0].covariance
    one = make_estimator(corner_sigma_px=1.0).estimate([1], corners, L, K).poses[0].covariance
    assert np.allclose(one, 4 * half)


TILTED = pose([0.35, 0.15, 0.0], [0.03, 0.02, 0.7])
"""A small, slightly tilted marker: with 0.5 px corner noise its two IPPE candidates are often close."""


def ambiguous_view(lower_error_is_wrong: bool) -> np.ndarray:
    """Noisy corners of ``TILTED`` whose two IPPE candidates are within a factor 1.5 in RMS and whose
    lower-error candidate is (or is not) the wrong flip."""
    exact = corners_of(TILTED)
    rng = np.random.default_rng(0)
    for _ in range(500):
        corners = exact + rng.normal(0, 0.5, exact.shape)
        best, second = ippe_candidates([single_observation(0, L, corners)], K)[0]
        errors = [rotation_angle(c.T[:3, :3], TILTED[:3, :3]) for c in (best, second)]
        if second.rms_px < 1.5 * best.rms_px and abs(errors[0] - errors[1]) > 0.1 \
                and (errors[0] > errors[1]) == lower_error_is_wrong:
            return corners
    raise AssertionError("no such view")


def error_deg(estimator: MarkerPoseEstimator, corners: np.ndarray) -> tuple[float, bool]:
    """Rotation error (deg) against ``TILTED`` of the estimator's pose of ``corners``, and its ambiguity flag."""
    found = estimator.estimate([0], corners[None], L, K).poses[0]
    return np.degrees(rotation_angle(found.T[:3, :3], TILTED[:3, :3])), found.ambiguous


@pytest.mark.parametrize("method", METHODS)
def test_an_ambiguous_view_follows_the_anchored_track(method):
    noisy = ambiguous_view(lower_error_is_wrong=True)
    fresh_error, fresh_flag = error_deg(make_estimator(method=method), noisy)
    tracked = make_estimator(method=method)
    assert not tracked.estimate([0], corners_of(TILTED)[None], L, K).poses[0].ambiguous
    tracked_error, tracked_flag = error_deg(tracked, noisy)
    stale = make_estimator(method=method, prior_max_age=2)
    stale.estimate([0], corners_of(TILTED)[None], L, K)
    for _ in range(2):
        stale.estimate([], np.zeros((0, 4, 2)), [], K)
    stale_error, _ = error_deg(stale, noisy)
    assert fresh_flag and tracked_flag
    assert fresh_error > 5.0 and tracked_error < fresh_error - 5.0
    assert stale_error == pytest.approx(fresh_error)


@pytest.mark.parametrize("method", METHODS)
def test_an_unanchored_track_is_not_followed(method):
    """A guess (the lower error of an ambiguous first view, here the wrong flip) must not decide the
    next ambiguous view, whose lower-error candidate is the right one."""
    wrong_first, right_next = ambiguous_view(lower_error_is_wrong=True), ambiguous_view(lower_error_is_wrong=False)
    estimator = make_estimator(method=method)
    first_error, _ = error_deg(estimator, wrong_first)
    next_error, next_flag = error_deg(estimator, right_next)
    fresh_error, _ = error_deg(make_estimator(method=method), right_next)
    assert next_flag and first_error > 5.0
    assert next_error == pytest.approx(fresh_error) and next_error < first_error - 5.0


@pytest.fixture(scope="module")
def scene():
    return make_scene("markers")


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("index", [0, 200, 450])
def test_a_board_gives_one_pose_from_all_its_markers(scene, method, index):
    board = map_from_poses("board", scene.marker_poses, scene.marker_length)
    T_cam_board = invert(scene.camera_pose(index))
    ids = list(board.markers) + [9]
    T_cam_loose = T_cam_board @ make_transform(np.eye(3), [0.0, -0.2, 0.0])
    corners = np.array([corners_of(T_cam_board @ board.markers[i].T_map_marker) for i in board.markers]
                       + [corners_of(T_cam_loose, 0.04)])
    result = make_estimator(method=method, marker_map=board).estimate(ids, corners, [0.0] * 6 + [0.04], K)
    found = {p.target: p for p in result.poses}
    assert sorted(found) == ["board", "marker/9"] and not result.failures
    assert np.allclose(found["board"].T, T_cam_board, atol=1e-7)
    assert found["board"].points == 24 and found["board"].marker_ids == tuple(board.markers)
    assert np.allclose(found["marker/9"].T, T_cam_loose, atol=1e-7)


@pytest.mark.parametrize("method", METHODS)
def test_a_board_seen_through_one_marker(scene, method):
    board = map_from_poses("board", scene.marker_poses, scene.marker_length)
    T_cam_board = invert(scene.camera_pose(100))
    corners = corners_of(T_cam_board @ board.markers[4].T_map_marker)[None]
    (found,) = make_estimator(method=method, marker_map=board).estimate([4], corners, 0.0, K).poses
    assert found.target == "board" and found.points == 4
    assert np.allclose(found.T, T_cam_board, atol=1e-7)


@pytest.mark.parametrize("method", METHODS)
def test_a_non_planar_map(method):
    """Two markers on perpendicular faces of a box: front (z towards the camera) and right side."""
    side = make_transform(matrix_from_rotvec([0.0, np.pi / 2, 0.0]), [0.06, 0.0, -0.06])
    box = MarkerMap("box", {1: MapMarker(1, 0.08, np.eye(4)), 2: MapMarker(2, 0.08, side)})
    T_cam_box = pose([0.2, 0.7, 0.1], [0.0, 0.02, 0.5])
    T_cam_markers = [T_cam_box @ m.T_map_marker for m in box.markers.values()]
    assert all(T[:3, 2] @ -T[:3, 3] > 0.1 for T in T_cam_markers)  # both face the camera
    corners = np.array([corners_of(T, 0.08) for T in T_cam_markers])
    (found,) = make_estimator(method=method, marker_map=box).estimate([1, 2], corners, 0.0, K).poses
    assert found.target == "box" and found.points == 8 and not found.ambiguous
    assert np.allclose(found.T, T_cam_box, atol=1e-7)


@pytest.mark.parametrize("method", METHODS)
def test_a_frame_of_markers_gives_each_the_pose_it_gets_alone(method):
    """The markers of a frame are solved together; each gets exactly its own pose, flag and covariance,
    the ambiguous view and an unusable marker included."""
    rng = np.random.default_rng(4)
    corners = [corners_of(T) + rng.normal(0, 0.5, (4, 2)) for T in POSES]
    corners += [ambiguous_view(lower_error_is_wrong=True), [[100, 100], [150, 100], [200, 100], [250, 100]]]
    ids, sides = [3, 1, 4, 0, 5], [L, L, L, L, L]
    together = make_estimator(method=method).estimate(ids, np.array(corners), sides, K)
    assert together.failures == {"degenerate_corners": 1}
    assert [p.target for p in together.poses] == ["marker/3", "marker/1", "marker/4", "marker/0"]
    for pose, marker_id, marker_corners_px in zip(together.poses, ids, corners, strict=False):
        (alone,) = make_estimator(method=method).estimate([marker_id], marker_corners_px[None], L, K).poses
        assert np.array_equal(pose.T, alone.T) and pose.rms_px == alone.rms_px
        assert pose.ambiguous == alone.ambiguous and np.array_equal(pose.covariance, alone.covariance)
    assert together.poses[3].ambiguous


@pytest.mark.parametrize("method", ["lm", "ippe+lm"])
def test_an_iteration_limit_too_low_fails_every_marker_as_not_converged(method):
    corners = np.array([corners_of(T) for T in POSES]) + np.random.default_rng(5).normal(0, 0.5, (3, 4, 2))
    result = make_estimator(method=method, max_iterations=1).estimate([1, 2, 3], corners, L, K)
    assert result.poses == [] and result.failures == {"not_converged": 3}
