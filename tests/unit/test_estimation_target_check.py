"""The trackability check: a rich texture passes; flat, one-corner and tiled images are warned about."""

import cv2
import numpy as np
import pytest

from services.estimation.targets.check import Trackability, check_image, repeated_fraction, spread
from services.synthetic import make_scene


@pytest.fixture(scope="module")
def texture():
    return make_scene("planar_target").texture


def shown(report: Trackability) -> Trackability:
    """``report``, its figures printed on a line of their own (``pytest -s``)."""
    print(f"\n{report.verdict}: {report.keypoints} keypoints, coverage {report.coverage:.2f}, entropy "
          f"{report.entropy:.2f}, repeated {report.repeated:.3f}")
    return report


@pytest.mark.parametrize("feature", ["orb", "sift"])
def test_a_rich_texture_is_good(texture, feature):
    report = shown(check_image(texture, feature))
    assert report.verdict == "good" and report.warnings == ()
    assert report.keypoints > 2000 and report.coverage > 0.9 and report.entropy > 0.85 and report.repeated < 0.1


def test_a_flat_image_is_poor(texture):
    flat = np.full(texture.shape, 128, np.uint8)
    cv2.circle(flat, (500, 300), 80, 60, -1)
    report = shown(check_image(cv2.GaussianBlur(flat, (0, 0), 2)))
    assert report.verdict == "poor" and report.keypoints < 100
    assert any("keypoints (want" in w for w in report.warnings)
    assert any("cover" in w for w in report.warnings)


@pytest.mark.parametrize("feature", ["orb", "sift"])
def test_a_tiled_pattern_is_poor_for_its_repeats(texture, feature):
    tiled = np.tile(texture[300:364, 300:380], (12, 13))[:texture.shape[0], :texture.shape[1]]
    report = shown(check_image(tiled, feature))
    assert report.verdict == "poor" and report.repeated > 0.9 and report.coverage > 0.9
    assert [w for w in report.warnings if "repeat" in w]


def test_texture_in_one_corner_is_fair_with_a_spread_warning(texture):
    corner = np.full(texture.shape, 128, np.uint8)
    corner[:250, :300] = texture[:250, :300]
    report = shown(check_image(corner))
    assert report.verdict == "fair" and report.coverage < 0.2
    assert any("cover" in w for w in report.warnings) and any("clustered" in w for w in report.warnings)


def test_spread_counts_cells_and_evenness():
    assert spread(np.zeros((0, 2), np.float32), (80, 80)) == (0.0, 0.0)
    assert spread(np.array([[5.0, 5.0]] * 10), (80, 80)) == (1 / 64, 0.0)
    grid = np.stack(np.meshgrid(np.arange(8) * 10 + 5.0, np.arange(8) * 10 + 5.0), axis=-1).reshape(-1, 2)
    assert spread(grid, (80, 80)) == (1.0, pytest.approx(1.0))


def test_a_twin_is_a_near_descriptor_away_from_the_keypoint():
    rng = np.random.default_rng(4)
    descriptors = rng.integers(0, 256, (40, 32), dtype=np.uint8)
    keypoints = rng.uniform(0, 500, (40, 2)).astype(np.float32)
    levels = np.zeros(40, np.uint8)
    assert repeated_fraction(keypoints, descriptors, levels) == 0.0
    descriptors[1] = descriptors[0]
    keypoints[1] = keypoints[0] + 100
    assert repeated_fraction(keypoints, descriptors, levels) == 2 / 40
    keypoints[1] = keypoints[0] + 2
    assert repeated_fraction(keypoints, descriptors, levels) == 0.0
