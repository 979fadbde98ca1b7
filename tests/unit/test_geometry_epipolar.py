"""Fundamental matrices from calibration agree with OpenCV's estimate from matched points; undistortion
agrees with a distortion-free projection."""

import cv2
import numpy as np
import pytest

from services.estimation.bodies.correspondence import fundamental_matrices
from services.geometry.camera import project_points, undistort_pixels
from services.geometry.epipolar import epipolar_distances, matched_epipolar_distances, sampson_distances, skew
from services.geometry.se3 import invert, transform_points
from services.synthetic import make_scene


@pytest.fixture(scope="module")
def scene():
    return make_scene("ir_rig", camera_count=3)


def cloud(seed: int = 0, count: int = 60) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.uniform((-0.6, -0.4, 1.6), (0.6, 0.4, 3.0), (count, 3))


def ideal_pixels(camera, points_world):
    return project_points(transform_points(invert(camera.T_rig_camera), points_world), camera.K)


def test_skew_is_the_cross_product():
    v, w = np.array([0.3, -1.2, 2.0]), np.array([-0.7, 0.1, 0.4])
    np.testing.assert_allclose(skew(v) @ w, np.cross(v, w), atol=1e-15)


def test_undistort_pixels_inverts_the_distortion(scene):
    camera = scene.cameras[0]
    points_cam = transform_points(invert(camera.T_rig_camera), cloud())
    observed = project_points(points_cam, camera.K, camera.dist)
    np.testing.assert_allclose(undistort_pixels(observed, camera.K, camera.dist), project_points(points_cam, camera.K),
                               atol=1e-6)


def test_fundamental_matrices_match_opencv_up_to_scale(scene):
    points = cloud()
    for (b, a), F in fundamental_matrices(scene.cameras).items():
        pa, pb = ideal_pixels(scene.cameras[a], points), ideal_pixels(scene.cameras[b], points)
        estimated, _ = cv2.findFundamentalMat(pa, pb, cv2.FM_8POINT)
        estimated /= np.linalg.norm(estimated)
        assert min(np.linalg.norm(F - estimated), np.linalg.norm(F + estimated)) < 1e-6
        distances = epipolar_distances(F, pa, pb)
        assert distances.shape == (len(points), len(points))
        assert np.max(np.diag(distances)) < 1e-8
        assert np.median(distances[~np.eye(len(points), dtype=bool)]) > 1.0


def test_epipolar_distance_is_the_point_to_line_distance(scene):
    (b, a), F = next(iter(fundamental_matrices(scene.cameras).items()))
    point = cloud(count=1)
    pa, pb = ideal_pixels(scene.cameras[a], point), ideal_pixels(scene.cameras[b], point)
    line = F @ np.append(pa[0], 1.0)
    normal = line[:2] / np.linalg.norm(line[:2])
    shifted = pb + 0.7 * normal
    assert epipolar_distances(F, pa, shifted)[0, 0] == pytest.approx(0.7, rel=0.05)


def test_matched_epipolar_distances_are_the_diagonal_of_all_pairs():
    rng = np.random.default_rng(4)
    F = rng.normal(size=(3, 3))
    pa, pb = rng.uniform(0, 640, (30, 2)), rng.uniform(0, 480, (30, 2))
    matched = matched_epipolar_distances(F, pa, pb)
    assert matched.shape == (30, 2)
    assert np.allclose(matched.max(axis=1), np.diag(epipolar_distances(F, pa, pb)))
    line_b = F @ np.append(pa[0], 1.0)
    assert matched[0, 1] == pytest.approx(abs(line_b @ np.append(pb[0], 1.0)) / np.linalg.norm(line_b[:2]))


def test_sampson_distances_square_to_opencvs():
    rng = np.random.default_rng(4)
    F = rng.normal(size=(3, 3))
    pixels_a, pixels_b = rng.uniform(0, 640, (20, 2)), rng.uniform(0, 480, (20, 2))
    expected = [cv2.sampsonDistance(np.append(a, 1.0).reshape(3, 1), np.append(b, 1.0).reshape(3, 1), F)
                for a, b in zip(pixels_a, pixels_b, strict=True)]
    assert sampson_distances(F, pixels_a, pixels_b) ** 2 == pytest.approx(expected, rel=1e-9)
