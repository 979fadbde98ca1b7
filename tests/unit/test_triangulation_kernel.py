"""The compiled triangulation against libraries: its points are the minimisers scipy's least_squares finds on the
reprojection error through OpenCV's projection, its covariances the inverse of the Gauss-Newton information built
from OpenCV's own derivatives, and its DLT start (no refinement) that of cv2.triangulatePoints
(up to the rows' scaling) and of the NumPy batch; its closed-form 3x3 normal equations and inverse NumPy's."""

import cv2
import numpy as np
import pytest
from scipy.optimize import least_squares

from services.geometry.camera import undistort_pixels
from services.geometry.camera_stack import CameraStack
from services.geometry.se3 import invert
from services.geometry.triangulation import projection_matrix, reproject, triangulate_dlt_many
from services.geometry.triangulation_kernel import _inverse, _normal, triangulate_points

SIGMA_PX = 0.2


@pytest.fixture(scope="module")
def cameras(distorted_cameras):
    """Three cameras with a stronger distortion than the scene's (``tests/unit/conftest.py``)."""
    return distorted_cameras


def observed(cameras, count: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(truth (N, 3), pixels (N, C, 2) with 0.5 px noise, ideal (N, C, 2), seen (N, C))``, one point in three
    seen by two cameras only."""
    rng = np.random.default_rng(seed)
    truth = rng.uniform((-0.6, -0.4, 1.4), (0.6, 0.4, 3.0), (count, 3))
    pixels = np.stack([reproject(c, truth) for c in cameras], axis=1) + rng.normal(0.0, 0.5, (count, 3, 2))
    ideal = np.stack([undistort_pixels(pixels[:, c], camera.K, camera.dist) for c, camera in enumerate(cameras)],
                     axis=1)
    seen = np.ones((count, 3), bool)
    seen[::3, rng.integers(0, 3)] = False
    return truth, pixels, ideal, seen


def solve(cameras, pixels, ideal, seen, start=None, iterations=10):
    stack = CameraStack.of(cameras)
    return triangulate_points(stack.K, stack.dist, stack.R_camera_world, stack.t_camera_world, stack.projections,
                              pixels, ideal, seen, start, SIGMA_PX, iterations, 1e-10)


def opencv_residuals(cameras, pixels: np.ndarray, seen: np.ndarray, point: np.ndarray):
    """(2V,) observed - projected px over the seen cameras and (2V, 3) their derivatives, by cv2.projectPoints."""
    residuals, jacobians = [], []
    for camera, pixel, used in zip(cameras, pixels, seen, strict=True):
        if not used:
            continue
        T = invert(camera.T_rig_camera)
        projected, d = cv2.projectPoints(point.reshape(1, 1, 3), cv2.Rodrigues(T[:3, :3])[0], T[:3, 3], camera.K,
                                         camera.dist)
        residuals.append(pixel - projected.reshape(2))
        jacobians.append(-d[:, 3:6] @ T[:3, :3])
    return np.concatenate(residuals), np.vstack(jacobians)


def test_points_are_the_minimisers_scipy_finds_and_covariances_the_inverse_information(cameras):
    truth, pixels, ideal, seen = observed(cameras, 30, seed=4)
    points, residuals, rms, covariances = solve(cameras, pixels, ideal, seen)
    for n in range(len(truth)):
        reference = least_squares(lambda X, n=n: opencv_residuals(cameras, pixels[n], seen[n], X)[0], truth[n] + 0.01,
                                  method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15)
        np.testing.assert_allclose(points[n], reference.x, atol=1e-8)
        r, J = opencv_residuals(cameras, pixels[n], seen[n], points[n])
        np.testing.assert_allclose(residuals[n][seen[n]].ravel(), r, atol=1e-6)
        assert np.all(residuals[n][~seen[n]] == 0.0)
        assert rms[n] == pytest.approx(np.sqrt(np.sum(r**2) / np.count_nonzero(seen[n])), rel=1e-6)
        np.testing.assert_allclose(covariances[n], np.linalg.inv(J.T @ J) * SIGMA_PX**2, rtol=1e-5)
    assert np.median(np.linalg.norm(points - truth, axis=1)) > 1e-5


def test_without_refinement_the_start_is_opencv_dlt(cameras):
    a, b = cameras[0], cameras[2]
    truth, pixels, ideal, _ = observed(cameras, 20, seed=6)
    seen = np.zeros((len(truth), 3), bool)
    seen[:, [0, 2]] = True
    points = solve(cameras, pixels, ideal, seen, iterations=0)[0]
    Pa, Pb = (projection_matrix(c.K, invert(c.T_rig_camera)) for c in (a, b))
    homogeneous = cv2.triangulatePoints(Pa, Pb, ideal[:, 0].T, ideal[:, 2].T)
    np.testing.assert_allclose(points, (homogeneous[:3] / homogeneous[3]).T, atol=2e-4)
    projections = CameraStack.of(cameras).projections
    np.testing.assert_allclose(points, triangulate_dlt_many(projections, ideal, seen), atol=1e-9)
    assert np.median(np.linalg.norm(points - truth, axis=1)) > 1e-4


def test_a_given_start_reaches_the_dlt_s_minimum_and_a_point_seen_once_or_without_start_is_not_made(cameras):
    truth, pixels, ideal, seen = observed(cameras, 4, seed=8)
    seen[:] = True
    seen[1] = (True, False, False)
    from_start = solve(cameras, pixels, ideal, seen, start=truth + 0.02)[0]
    from_dlt = solve(cameras, pixels, ideal, seen)
    np.testing.assert_allclose(from_start[[0, 2, 3]], from_dlt[0][[0, 2, 3]], atol=1e-8)
    assert np.all(np.linalg.norm(from_dlt[0][[0, 2, 3]] - truth[[0, 2, 3]], axis=1) < 0.005)
    assert np.all(np.isnan(from_dlt[0][1])) and from_dlt[2][1] == np.inf and np.all(np.isnan(from_dlt[3][1]))
    parallel = solve(cameras[:2], np.full((1, 2, 2), 300.0), np.full((1, 2, 2), 300.0), np.ones((1, 2), bool),
                     start=np.full((1, 3), np.nan))
    assert np.all(np.isnan(parallel[0])) and parallel[2][0] == np.inf


def test_the_closed_form_3x3_inverse_is_numpys_and_the_pseudo_inverse_where_singular():
    rng = np.random.default_rng(7)
    for _ in range(50):
        J = rng.normal(size=(6, 3)) * rng.uniform(1e-3, 1e3, size=3)
        information = J.T @ J
        np.testing.assert_allclose(_inverse(information), np.linalg.inv(information), rtol=1e-9)
        np.testing.assert_allclose(_normal(J, J[:, 0])[0], information, rtol=1e-12)
        np.testing.assert_allclose(_normal(J, J[:, 0])[1], J.T @ J[:, 0], rtol=1e-12)
    ray = np.outer([1.0, 2.0, -1.0], [1.0, 2.0, -1.0]) + np.outer([0.0, 1.0, 2.0], [0.0, 1.0, 2.0])  # rank 2
    np.testing.assert_allclose(_inverse(ray), np.linalg.pinv(ray), atol=1e-12)
