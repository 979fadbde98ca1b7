"""Colour blobs: the hue model's circular statistics against scipy, the mask against ``cv2.inRange``,
and the blobs of rendered coloured discs against their true centre, area and perimeter."""

import math

import cv2
import numpy as np
import pytest
from scipy import stats

from services.detection.blobs.bright import BlobFlag
from services.detection.blobs.colour import (
    ColourBlobParams,
    HueModel,
    circular_mean_spread,
    colour_mask,
    detect_colour_blobs,
    hue_table,
    to_hsv,
)
from tests.blob_images import disc_coverage

SHAPE = (240, 320)
GREY = (110, 110, 110)
RED, GREEN, BLUE = (30, 20, 210), (40, 190, 30), (200, 60, 20)


def painted(discs: list[tuple[float, float, float, tuple[int, int, int]]], noise: float = 0.0,
            seed: int = 0) -> np.ndarray:
    """(H, W, 3) uint8 BGR: grey with anti-aliased discs (x, y, radius px, BGR colour) and Gaussian noise."""
    image = np.tile(np.array(GREY, np.float64), (*SHAPE, 1))
    for x, y, radius, colour in discs:
        share = disc_coverage([(x, y, radius)], SHAPE)[..., None]
        image = image * (1.0 - share) + np.array(colour, np.float64) * share
    image += np.random.default_rng(seed).normal(0.0, noise, image.shape)
    return np.clip(image + 0.5, 0, 255).astype(np.uint8)


def test_circular_mean_and_spread_match_scipy_across_the_wrap():
    rng = np.random.default_rng(1)
    for centre in (0.05, 3.0, 6.2):
        angles = (centre + rng.normal(0.0, 0.2, 500)) % (2 * math.pi)
        mean, spread = circular_mean_spread(angles)
        assert mean == pytest.approx(stats.circmean(angles), abs=1e-9)
        assert spread == pytest.approx(stats.circstd(angles), abs=1e-9)


def test_a_red_sample_straddling_hue_zero_gives_a_mean_near_zero():
    image = painted([(100.0, 100.0, 30.0, RED), (160.0, 100.0, 1.0, GREY)], noise=6.0)
    hues = to_hsv(image)[90:110, 90:110, 0]
    assert (hues < 10).any() and (hues > 245).any()
    model = HueModel.from_sample(image, (90, 90, 20, 20))
    true_hue = float(to_hsv(np.array([[RED]], np.uint8))[0, 0, 0]) * 360.0 / 256.0
    assert abs((model.hue_deg - true_hue + 180.0) % 360.0 - 180.0) < 1.5
    assert colour_mask(image, model)[90:110, 90:110].mean() > 0.99


@pytest.mark.parametrize("colour", [GREEN, BLUE, RED])
def test_mask_matches_opencv_in_range_on_the_same_window(colour):
    image = painted([(100.0, 100.0, 30.0, colour), (220.0, 150.0, 25.0, GREEN if colour != GREEN else BLUE)],
                    noise=8.0, seed=2)
    model = HueModel.from_sample(image, (90, 90, 20, 20))
    hsv = to_hsv(image)
    codes = np.flatnonzero(hue_table(model, ColourBlobParams()))
    runs = np.split(codes, np.flatnonzero(np.diff(codes) > 1) + 1)
    low_s, low_v = math.ceil(model.min_saturation), math.ceil(model.min_value)
    expected = np.zeros(SHAPE, bool)
    for run in runs:
        expected |= cv2.inRange(hsv, (int(run[0]), low_s, low_v), (int(run[-1]), 255, 255)) > 0
    assert len(runs) == (2 if colour == RED else 1)
    np.testing.assert_array_equal(colour_mask(image, model), expected)


def test_blobs_of_the_sampled_colour_have_their_true_centre_area_and_perimeter():
    discs = [(60.3, 70.6, 18.0, RED), (200.7, 60.2, 12.0, RED), (150.0, 170.0, 20.0, GREEN),
             (260.2, 180.4, 25.0, RED), (80.0, 180.0, 15.0, BLUE)]
    image = painted(discs, noise=3.0, seed=3)
    model = HueModel.from_sample(image, (55, 65, 10, 10))
    blobs = detect_colour_blobs(image, model)
    reds = sorted((d for d in discs if d[3] == RED), key=lambda d: -d[2])
    assert len(blobs) == len(reds) and not blobs.flags.any()
    for k, (x, y, radius, _) in enumerate(reds):
        assert blobs.centroids[k] == pytest.approx((x, y), abs=0.2)
        assert blobs.area[k] == pytest.approx(math.pi * radius**2, rel=0.03)
        assert blobs.perimeter[k] == pytest.approx(2 * math.pi * radius, rel=0.04)
        assert blobs.circularity[k] > 0.9
    contours, _ = cv2.findContours(colour_mask(image, model).view(np.uint8), cv2.RETR_EXTERNAL,
                                   cv2.CHAIN_APPROX_NONE)
    lengths = sorted((cv2.arcLength(c, True) for c in contours), reverse=True)
    np.testing.assert_allclose(blobs.perimeter, lengths, rtol=0.06)


def test_two_overlapping_markers_are_flagged_merged_and_one_cut_by_the_border_clipped_and_occluded():
    image = painted([(100.0, 100.0, 12.0, RED), (118.0, 104.0, 12.0, RED), (5.0, 200.0, 12.0, RED)])
    blobs = detect_colour_blobs(image, HueModel.from_sample(image, (95, 95, 10, 10)))
    assert len(blobs) == 2
    assert blobs.flags[0] == BlobFlag.MERGED and blobs.flags[1] == BlobFlag.CLIPPED | BlobFlag.OCCLUDED


def test_bad_input_is_refused_with_a_reason():
    image = painted([(100.0, 100.0, 12.0, RED)])
    with pytest.raises(ValueError, match="not inside"):
        HueModel.from_sample(image, (310, 230, 20, 20))
    with pytest.raises(ValueError, match="bgr8"):
        detect_colour_blobs(image[..., 0], HueModel(0.0, 2.0, 50.0, 50.0))
    with pytest.raises(ValueError, match="width"):
        ColourBlobParams(width=-1.0)
