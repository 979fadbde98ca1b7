"""Triangulation against OpenCV and ground truth: DLT equals cv2.triangulatePoints, the midpoint equals the DLT
on exact rays, the refinement reaches the true point through the distortion, and the covariance predicts the
spread of the errors."""

import cv2
import numpy as np
import pytest

from services.geometry.camera import undistort_pixels
from services.geometry.camera_stack import CameraStack
from services.geometry.se3 import invert
from services.geometry.triangulation import (
    camera_rays,
    projection_matrix,
    reproject,
    triangulate,
    triangulate_dlt,
    triangulate_many,
    triangulate_midpoint,
)
from services.synthetic import make_scene

SIGMA_PX = 0.05
TRIALS = 400


@pytest.fixture(scope="module")
def cameras():
    return make_scene("ir_rig", camera_count=3, width=1280, height=1024, baseline=1.0).cameras


def points(seed: int = 0, count: int = 20) -> np.ndarray:
    return np.random.default_rng(seed).uniform((-0.5, -0.3, 1.6), (0.5, 0.3, 2.8), (count, 3))


def test_dlt_matches_opencv(cameras):
    a, b = cameras[0], cameras[2]
    Pa, Pb = (projection_matrix(c.K, invert(c.T_rig_camera)) for c in (a, b))
    truth = points()
    rng = np.random.default_rng(1)
    pa = undistort_pixels(reproject(a, truth), a.K, a.dist) + rng.normal(0.0, 0.3, (len(truth), 2))
    pb = undistort_pixels(reproject(b, truth), b.K, b.dist) + rng.normal(0.0, 0.3, (len(truth), 2))
    homogeneous = cv2.triangulatePoints(Pa, Pb, pa.T, pb.T)
    opencv = (homogeneous[:3] / homogeneous[3]).T
    ours = np.array([triangulate_dlt(np.array([Pa, Pb]), np.array([x, y])) for x, y in zip(pa, pb, strict=True)])
    assert np.max(np.linalg.norm(ours - opencv, axis=1)) < 1e-4
    assert np.median(np.linalg.norm(ours - truth, axis=1)) > 1e-5


def test_midpoint_equals_dlt_on_exact_rays(cameras):
    a, b = cameras[0], cameras[1]
    projections = np.array([projection_matrix(c.K, invert(c.T_rig_camera)) for c in (a, b)])
    for truth in points(2):
        origin_a, ray_a = camera_rays(a, reproject(a, truth))
        origin_b, ray_b = camera_rays(b, reproject(b, truth))
        midpoint = triangulate_midpoint(np.array([origin_a, origin_b]), np.vstack([ray_a, ray_b]))
        ideal = np.array([undistort_pixels(reproject(c, truth), c.K, c.dist)[0] for c in (a, b)])
        np.testing.assert_allclose(midpoint, triangulate_dlt(projections, ideal), atol=1e-7)
        np.testing.assert_allclose(midpoint, truth, atol=1e-7)


def test_parallel_rays_are_refused():
    with pytest.raises(ValueError, match="parallel"):
        triangulate_midpoint(np.array([[0.0, 0, 0], [1.0, 0, 0]]), np.array([[0.0, 0, 1], [0.0, 0, 2]]))


def test_refinement_reaches_the_true_point_through_distortion(cameras):
    truth = np.array([0.2, -0.1, 2.2])
    pixels = np.array([reproject(c, truth)[0] for c in cameras])
    found = triangulate_many(CameraStack.of(cameras), pixels[None], np.ones((1, 3), bool), SIGMA_PX,
                             start=(truth + np.array([0.01, -0.02, 0.05]))[None])
    np.testing.assert_allclose(found.points[0], truth, atol=1e-9)
    assert np.max(np.abs(found.residuals)) < 1e-6


def test_point_carries_views_indices_and_residual(cameras):
    truth = np.array([-0.1, 0.05, 2.0])
    pixels = np.array([reproject(c, truth)[0] for c in cameras])
    pixels[1] += (3.0, 0.0)
    result = triangulate(cameras, pixels, SIGMA_PX, camera_indices=[0, 1, 2], blob_indices=[4, 0, 7])
    assert result.views == 3 and result.blob_indices == (4, 0, 7)
    assert 0.5 < result.rms_px < 3.0


@pytest.mark.parametrize("count", [2, 3])
def test_covariance_predicts_the_error_spread(cameras, count):
    """Along each principal axis of the predicted covariance, the observed standard deviation
    of the errors is within 30 % of the predicted one."""
    views = cameras[:count]
    truth = np.array([0.15, 0.08, 2.0])
    exact = np.array([reproject(c, truth)[0] for c in views])
    rng = np.random.default_rng(3)
    results = [triangulate(views, exact + rng.normal(0.0, SIGMA_PX, exact.shape), SIGMA_PX) for _ in range(TRIALS)]
    errors = np.array([r.point - truth for r in results])
    predicted = np.mean([r.covariance for r in results], axis=0)
    variances, axes = np.linalg.eigh(predicted)
    observed = np.std(errors @ axes, axis=0)
    np.testing.assert_allclose(observed, np.sqrt(variances), rtol=0.3)
