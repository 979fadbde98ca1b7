"""Projection-matrix DLT and its RQ decomposition, against known synthetic cameras and
cv2.decomposeProjectionMatrix."""

import cv2
import numpy as np
import pytest

from services.geometry.camera_dlt import decompose_projection, projection_dlt, rq
from services.geometry.homography import DegenerateError
from services.geometry.rotation import matrix_from_rotvec, rotation_angle
from services.geometry.se3 import make_transform, transform_points


def random_camera(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A K with skew and unequal focal lengths, and a ``T_camera_world`` about 2 m from the origin."""
    f = rng.uniform(400, 1200)
    K = np.array([[f, rng.uniform(-2, 2), rng.uniform(280, 360)],
                  [0.0, f * rng.uniform(0.95, 1.05), rng.uniform(200, 280)], [0.0, 0.0, 1.0]])
    R = matrix_from_rotvec(rng.uniform(-np.pi, np.pi, 3))
    return K, make_transform(R, np.array([*rng.uniform(-0.2, 0.2, 2), 2.0]) - R @ rng.uniform(-0.3, 0.3, 3))


def project(K: np.ndarray, T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(N, 2) pixels through the full K (with skew), no distortion."""
    p = transform_points(T, points) @ K.T
    return p[:, :2] / p[:, 2:]


@pytest.mark.parametrize("seed", range(10))
def test_exact_data_gives_the_exact_camera(seed):
    rng = np.random.default_rng(seed)
    K, T = random_camera(rng)
    points = rng.uniform(-0.5, 0.5, (12, 3))
    P = projection_dlt(points, project(K, T, points))
    K_found, R, t = decompose_projection(P)
    assert np.allclose(K_found, K, rtol=1e-8, atol=1e-6)
    assert np.allclose(R, T[:3, :3], atol=1e-9)
    assert np.allclose(t, T[:3, 3], atol=1e-9)
    depth = np.column_stack([points, np.ones(len(points))]) @ P[2]
    assert np.allclose(depth, transform_points(T, points)[:, 2], atol=1e-9)


@pytest.mark.parametrize("seed", range(10))
def test_noisy_data_gives_a_close_camera(seed):
    rng = np.random.default_rng(100 + seed)
    K, T = random_camera(rng)
    points = rng.uniform(-0.5, 0.5, (60, 3))
    K_found, R, t = decompose_projection(projection_dlt(points, project(K, T, points) + rng.normal(0, 0.5, (60, 2))))
    assert np.allclose(np.diag(K_found)[:2], np.diag(K)[:2], rtol=0.02)
    assert np.allclose(K_found[:2, 2], K[:2, 2], atol=10.0)
    assert np.degrees(rotation_angle(R, T[:3, :3])) < 0.5
    assert np.linalg.norm(t - T[:3, 3]) < 0.02 * np.linalg.norm(T[:3, 3])


@pytest.mark.parametrize("seed", range(10))
@pytest.mark.parametrize("scale", [1.0, -3.0])
def test_decomposition_matches_cv2(seed, scale):
    rng = np.random.default_rng(200 + seed)
    K, T = random_camera(rng)
    P = K @ T[:3]
    K_found, R, t = decompose_projection(scale * P)
    K_cv, R_cv, centre = cv2.decomposeProjectionMatrix(P)[:3]
    assert np.allclose(K_found, K_cv / K_cv[2, 2], rtol=1e-9, atol=1e-7)
    assert np.allclose(R, R_cv, atol=1e-9)
    assert np.allclose(-R.T @ t, centre[:3, 0] / centre[3, 0], atol=1e-9)
    assert np.linalg.det(R) == pytest.approx(1.0) and np.all(np.diag(K_found) > 0) and K_found[2, 2] == 1.0


@pytest.mark.parametrize("seed", range(5))
def test_rq_factors_a_matrix(seed):
    M = np.random.default_rng(300 + seed).normal(size=(3, 3))
    U, Q = rq(M)
    assert np.allclose(U @ Q, M) and np.allclose(np.tril(U, -1), 0) and np.allclose(Q @ Q.T, np.eye(3))


@pytest.mark.parametrize(("points", "message"), [
    (np.column_stack([np.random.default_rng(1).uniform(-1, 1, (10, 2)), np.zeros(10)]), "coplanar"),
    (np.outer(np.linspace(-1, 1, 10), [1.0, 2.0, 3.0]), "coplanar or collinear"),
    (np.random.default_rng(2).uniform(-1, 1, (5, 3)), "at least 6"),
    (np.ones((8, 3)), "coincide"),
])
def test_degenerate_points_are_refused(points, message):
    K, T = random_camera(np.random.default_rng(3))
    pixels = project(K, T, points)
    with pytest.raises(DegenerateError, match=message):
        projection_dlt(points, pixels)


def test_nearly_coplanar_noisy_points_are_ill_determined():
    rng = np.random.default_rng(4)
    K, T = random_camera(rng)
    points = np.column_stack([rng.uniform(-0.5, 0.5, (30, 2)), rng.normal(0, 1e-4, 30)])
    with pytest.raises(DegenerateError, match="ill-determined"):
        projection_dlt(points, project(K, T, points) + rng.normal(0, 1.0, (30, 2)))


def test_a_singular_projection_matrix_is_refused():
    with pytest.raises(DegenerateError, match="singular"):
        decompose_projection(np.array([[1.0, 0, 0, 0], [0, 1.0, 0, 0], [1.0, 1.0, 0, 1.0]]))
