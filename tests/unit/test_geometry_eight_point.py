"""The normalised eight-point algorithm against the truth, OpenCV's FM_8POINT and its USAC essential matrix."""

import cv2
import numpy as np
import pytest

from services.geometry.camera import intrinsics, project_points
from services.geometry.eight_point import eight_point_fundamental, essential_from_fundamental
from services.geometry.epipolar import fundamental_matrix, skew
from services.geometry.homography import DegenerateError
from services.geometry.rotation import matrix_from_rotvec, rotation_angle
from services.geometry.se3 import make_transform, transform_points

K = intrinsics(640, 480, 64.0)


def same_up_to_sign(A: np.ndarray, B: np.ndarray) -> float:
    """Largest element difference of two matrices scaled to unit norm, the sign of B chosen to fit A."""
    A, B = A / np.linalg.norm(A), B / np.linalg.norm(B)
    return float(min(np.abs(A - B).max(), np.abs(A + B).max()))


def same_fundamental(F: np.ndarray, G: np.ndarray) -> float:
    """``same_up_to_sign`` of two fundamental matrices compared as ``K^T F K``: F's elements span six
    orders of magnitude in pixels, the normalised image's matrix has all of them near one."""
    return same_up_to_sign(K.T @ F @ K, K.T @ G @ K)


def correspondences(seed: int, noise_px: float, count: int = 200):
    """(pixels_a, pixels_b, T_b_a) of random points 3-8 m in front of camera a, seen after a known motion
    (a 0.5 m baseline in a random direction)."""
    rng = np.random.default_rng(seed)
    points_a = rng.uniform([-2.0, -1.5, 3.0], [2.0, 1.5, 8.0], (count, 3))
    baseline = rng.normal(0.0, 1.0, 3)
    T_b_a = make_transform(matrix_from_rotvec(rng.normal(0.0, 0.1, 3)), 0.5 * baseline / np.linalg.norm(baseline))
    pixels_a = project_points(points_a, K) + rng.normal(0.0, noise_px, (count, 2))
    pixels_b = project_points(transform_points(T_b_a, points_a), K) + rng.normal(0.0, noise_px, (count, 2))
    return pixels_a, pixels_b, T_b_a


@pytest.mark.parametrize("seed", range(5))
def test_noise_free_matches_the_truth_and_opencv(seed):
    pixels_a, pixels_b, T_b_a = correspondences(seed, 0.0)
    F = eight_point_fundamental(pixels_a, pixels_b)
    assert np.linalg.matrix_rank(F, tol=1e-9) == 2
    assert same_fundamental(F, fundamental_matrix(K, K, T_b_a)) < 1e-10
    F_cv, _ = cv2.findFundamentalMat(pixels_a, pixels_b, cv2.FM_8POINT)
    assert same_fundamental(F, F_cv) < 1e-6
    E = essential_from_fundamental(F, K, K)
    assert same_up_to_sign(E, skew(T_b_a[:3, 3]) @ T_b_a[:3, :3]) < 1e-8
    assert np.allclose(np.linalg.svd(E, compute_uv=False), [1.0, 1.0, 0.0], atol=1e-12)


@pytest.mark.parametrize("seed", range(5))
def test_noisy_agrees_with_opencv_and_the_usac_essential_matrix(seed):
    pixels_a, pixels_b, T_b_a = correspondences(seed, 0.5)
    F = eight_point_fundamental(pixels_a, pixels_b)
    F_cv, _ = cv2.findFundamentalMat(pixels_a, pixels_b, cv2.FM_8POINT)
    assert same_fundamental(F, F_cv) < 2e-3

    E_usac, mask = cv2.findEssentialMat(pixels_a, pixels_b, K, method=cv2.USAC_MAGSAC, prob=0.999, threshold=1.0)
    poses = []
    for E in (essential_from_fundamental(F, K, K), E_usac[:3]):
        _, R, t, _ = cv2.recoverPose(E, pixels_a, pixels_b, K)
        poses.append((R, t.ravel()))
    (R_8, t_8), (R_usac, t_usac) = poses
    assert np.degrees(rotation_angle(R_8, R_usac)) < 0.2
    assert np.degrees(np.arccos(np.clip(t_8 @ t_usac, -1.0, 1.0))) < 1.0
    truth = T_b_a[:3, 3] / np.linalg.norm(T_b_a[:3, 3])
    assert np.degrees(rotation_angle(R_8, T_b_a[:3, :3])) < 0.6
    assert np.degrees(np.arccos(np.clip(t_8 @ truth, -1.0, 1.0))) < 3.0


def test_too_few_points_are_refused():
    pixels_a, pixels_b, _ = correspondences(0, 0.0, count=7)
    with pytest.raises(DegenerateError):
        eight_point_fundamental(pixels_a, pixels_b)
