"""``calibration_check.check_focal`` on a map made from known geometry: six keyframes turning 10-15 deg
around 400 points 3-5 m away, their keypoints the points projected by the true camera matrix plus
0.5 px noise. Given the true matrix, the focal lengths stay and the check passes; given one 20 % off,
freed they come back to within 3 % of the truth and the check calls the matrix suspect."""

from __future__ import annotations

import numpy as np
import pytest

from services.geometry.rotation import matrix_from_rotvec
from services.geometry.se3 import make_transform
from services.slam.calibration_check import check_focal
from services.slam.features import FrameFeatures
from services.slam.map.database import MapDatabase

K_TRUE = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])
SIZE = (640, 480)


def made_map(keyframes: int = 6, seed: int = 2) -> MapDatabase:
    """The map of the module docstring, of its first ``keyframes`` keyframes."""
    rng = np.random.default_rng(seed)
    points = rng.uniform([-2.0, -1.5, 3.0], [2.0, 1.5, 5.0], (400, 3))
    slam_map = MapDatabase(1.2, 8)
    for k in range(keyframes):
        angle = np.radians(-15 + 6 * k)
        T = make_transform(matrix_from_rotvec([0.3 * angle, angle, 0.05 * k]), [0.15 * k - 0.4, 0.05 * k, 0.1 * k])
        camera = points @ T[:3, :3].T + T[:3, 3]
        pixels = camera[:, :2] / camera[:, 2:] * K_TRUE[[0, 1], [0, 1]] + K_TRUE[:2, 2] + rng.normal(0, 0.5, (400, 2))
        count = len(pixels)
        features = FrameFeatures(pixels=pixels, levels=np.zeros(count, np.int64),
                                 angles=np.zeros(count, np.float32),
                                 descriptors=rng.integers(0, 256, (count, 32), dtype=np.uint8),
                                 sigmas=np.ones(count))
        slam_map.add_keyframe(k, T, features, np.full(count, -1, np.int64))
    for index, position in enumerate(points):
        slam_map.add_point(position, {k: index for k in slam_map.keyframes})
    return slam_map


@pytest.fixture(scope="module")
def slam_map() -> MapDatabase:
    return made_map()


def test_the_true_camera_matrix_passes(slam_map):
    check = check_focal(slam_map, K_TRUE, SIZE)
    assert check is not None and not check.suspect, check.line()
    assert abs(check.free_fx / 500.0 - 1) < 0.03 and abs(check.free_fy / 500.0 - 1) < 0.03, check.line()
    assert check.error_free_px == pytest.approx(check.error_fixed_px, rel=0.02)


@pytest.mark.parametrize("scale", [0.8, 1.2])
def test_a_focal_length_20_percent_off_is_suspect_and_freed_comes_back(slam_map, scale):
    K = K_TRUE.copy()
    K[[0, 1], [0, 1]] *= scale
    check = check_focal(slam_map, K, SIZE)
    assert check is not None and check.suspect, check.line()
    assert abs(check.free_fx / 500.0 - 1) < 0.03 and abs(check.free_fy / 500.0 - 1) < 0.03, check.line()
    assert "when free" in check.line()


def test_a_map_of_two_keyframes_is_not_checked():
    assert check_focal(made_map(keyframes=2), K_TRUE, SIZE) is None
