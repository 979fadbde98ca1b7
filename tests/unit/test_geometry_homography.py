"""Normalised DLT and pose from homography, cross-checked against OpenCV and exact synthetic views."""

import cv2
import numpy as np
import pytest

from services.geometry.camera import project_points
from services.geometry.homography import DegenerateError, homography_dlt, pose_from_homography, transfer_errors
from services.geometry.rotation import matrix_from_rotvec, rotation_angle
from services.geometry.se3 import make_transform, transform_points

K = np.array([[600.0, 0.0, 319.5], [0.0, 600.0, 239.5], [0.0, 0.0, 1.0]])


def view(T_cam_plane: np.ndarray, plane_points: np.ndarray) -> np.ndarray:
    points = np.column_stack([plane_points, np.zeros(len(plane_points))])
    return project_points(transform_points(T_cam_plane, points), K).reshape(-1, 2)


@pytest.mark.parametrize("seed", range(20))
def test_dlt_matches_cv2_find_homography(seed):
    rng = np.random.default_rng(seed)
    src = rng.uniform(-0.2, 0.2, (30, 2))
    T = make_transform(matrix_from_rotvec(rng.uniform(-0.6, 0.6, 3)), [*rng.uniform(-0.1, 0.1, 2), 1.0])
    dst = view(T, src) + rng.normal(0, 0.3, (30, 2))
    ours = homography_dlt(src, dst)
    theirs, _ = cv2.findHomography(src, dst, 0)
    probe = rng.uniform(-0.2, 0.2, (50, 2))

    def warp(H: np.ndarray, points: np.ndarray) -> np.ndarray:
        return cv2.perspectiveTransform(points.reshape(-1, 1, 2), H).reshape(-1, 2)

    # OpenCV refines its DLT by Levenberg-Marquardt: with 0.3 px noise the two agree to a tenth
    # of a pixel, and the DLT's residual is within a few percent of the refined one.
    assert np.max(np.linalg.norm(warp(ours, probe) - warp(theirs, probe), axis=1)) < 0.1
    residual = {name: np.sqrt(np.mean(np.sum((warp(H, src) - dst) ** 2, axis=1)))
                for name, H in (("ours", ours), ("theirs", theirs))}
    assert residual["ours"] <= 1.05 * residual["theirs"]


def test_dlt_is_exact_on_four_noise_free_corners():
    corners = np.array([[-0.025, 0.025], [0.025, 0.025], [0.025, -0.025], [-0.025, -0.025]])
    T = make_transform(matrix_from_rotvec([0.3, -0.2, 0.1]), [0.02, -0.01, 0.4])
    H = homography_dlt(corners, view(T, corners))
    assert np.allclose(cv2.perspectiveTransform(corners.reshape(-1, 1, 2), H).reshape(-1, 2), view(T, corners),
                       atol=1e-8)


@pytest.mark.parametrize("seed", range(20))
def test_pose_from_homography_recovers_the_plane_pose(seed):
    rng = np.random.default_rng(100 + seed)
    T = make_transform(matrix_from_rotvec(rng.uniform(-0.8, 0.8, 3)), [*rng.uniform(-0.2, 0.2, 2),
                                                                        rng.uniform(0.3, 2.0)])
    src = rng.uniform(-0.1, 0.1, (12, 2))
    found = pose_from_homography(homography_dlt(src, view(T, src)), K)
    assert rotation_angle(found[:3, :3], T[:3, :3]) < 1e-7
    assert np.allclose(found[:3, 3], T[:3, 3], atol=1e-9)


def test_pose_is_in_front_of_the_camera_whatever_the_homography_sign():
    src = np.array([[-0.05, 0.05], [0.05, 0.05], [0.05, -0.05], [-0.05, -0.05]])
    T = make_transform(matrix_from_rotvec([0.1, 0.2, 0.0]), [0.0, 0.0, 0.5])
    H = homography_dlt(src, view(T, src))
    assert pose_from_homography(-H, K)[2, 3] == pytest.approx(0.5)


@pytest.mark.parametrize("src", [
    np.array([[0.0, 0.0], [1.0, 1.0], [2.0, 2.0], [3.0, 3.0]]),  # collinear
    np.zeros((4, 2)),  # coincident
    np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]]),  # too few
])
def test_degenerate_correspondences_are_refused(src):
    with pytest.raises(DegenerateError):
        homography_dlt(src, src * 2 + 1)


def test_transfer_errors_both_ways():
    H = np.array([[1.1, 0.02, 5.0], [-0.03, 0.95, -3.0], [1e-4, -2e-4, 1.0]])
    src = np.random.default_rng(1).uniform(0, 600, (20, 2))
    mapped = np.hstack([src, np.ones((20, 1))]) @ H.T
    dst = mapped[:, :2] / mapped[:, 2:]
    assert np.allclose(transfer_errors(H, src, dst), 0.0, atol=1e-9)
    moved = dst + [0.0, 2.0]
    errors = transfer_errors(H, src, moved)
    assert np.allclose(errors[:, 1], 2.0) and np.all(errors[:, 0] > 0.5)
