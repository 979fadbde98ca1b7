"""The stacked cameras' projection and its closed-form derivatives against cv2.projectPoints, and the batched
triangulation against the one-point form."""

import cv2
import numpy as np
import pytest

from services.geometry.camera_stack import CameraStack
from services.geometry.se3 import invert
from services.geometry.triangulation import reproject, triangulate, triangulate_many

SIGMA_PX = 0.1


@pytest.fixture(scope="module")
def cameras(distorted_cameras):
    """Three cameras with a stronger distortion than the scene's (``tests/unit/conftest.py``)."""
    return distorted_cameras


def points(seed: int = 0, count: int = 25) -> np.ndarray:
    return np.random.default_rng(seed).uniform((-0.8, -0.6, 1.2), (0.8, 0.6, 3.0), (count, 3))


def test_pixels_and_jacobians_match_opencv(cameras):
    world = points()
    pixels, jacobians = CameraStack.of(cameras).project_with_jacobians(world)
    for c, camera in enumerate(cameras):
        T_camera_world = invert(camera.T_rig_camera)
        expected, d_opencv = cv2.projectPoints(world.reshape(-1, 1, 3), cv2.Rodrigues(T_camera_world[:3, :3])[0],
                                               T_camera_world[:3, 3], camera.K, camera.dist)
        np.testing.assert_allclose(pixels[:, c], expected.reshape(-1, 2), atol=1e-9)
        d_world = d_opencv[:, 3:6].reshape(-1, 2, 3) @ T_camera_world[:3, :3]
        np.testing.assert_allclose(jacobians[:, c], d_world, rtol=1e-7, atol=1e-6)


def test_points_behind_a_camera_project_to_nan(cameras):
    stack = CameraStack.of(cameras)
    behind = cameras[0].T_rig_camera[:3, 3] - 0.5 * cameras[0].T_rig_camera[:3, 2]
    projected = stack.project(np.vstack([points(count=2), behind]))
    assert np.all(np.isfinite(projected[:2])) and np.all(np.isnan(projected[2, 0]))
    np.testing.assert_array_equal(np.isnan(projected[2, :, 0]), stack.depths(behind)[0] <= 0)


def test_many_points_with_their_own_views_equal_one_at_a_time(cameras):
    rng = np.random.default_rng(5)
    world = points(seed=1, count=12)
    pixels = np.stack([reproject(c, world) for c in cameras], axis=1) + rng.normal(0.0, 0.5, (len(world), 3, 2))
    seen = np.ones((len(world), 3), bool)
    seen[::3, 0] = False
    seen[1::3, 2] = False
    found = triangulate_many(CameraStack.of(cameras), pixels, seen, SIGMA_PX)
    for n in range(len(world)):
        views = np.flatnonzero(seen[n])
        one = triangulate([cameras[c] for c in views], pixels[n, views], SIGMA_PX)
        np.testing.assert_allclose(found.points[n], one.point, atol=1e-9)
        np.testing.assert_allclose(found.covariances[n], one.covariance, rtol=1e-6, atol=1e-15)
        assert found.rms_px[n] == pytest.approx(one.rms_px, abs=1e-9)
        assert np.all(found.residuals[n, ~seen[n]] == 0.0)
        assert np.linalg.norm(found.points[n] - world[n]) < 0.01


def test_a_point_seen_once_is_not_made(cameras):
    found = triangulate_many(CameraStack.of(cameras), np.full((1, 3, 2), 400.0), np.array([[True, False, False]]),
                             SIGMA_PX)
    assert np.all(np.isnan(found.points[0])) and found.rms_px[0] == np.inf
