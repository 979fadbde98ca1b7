"""IR blob detection on anti-aliased discs with known centres: subpixel centroids, flags for merged,
cut and clipped blobs, the filters; the components and weighted centroids cross-checked against
``cv2.connectedComponentsWithStats`` and a plain numpy weighted mean."""

import math

import cv2
import numpy as np
import pytest

from services.detection.blobs.bright import BlobFlag, Blobs, IrBlobParams, ShapeParams, detect_ir_blobs
from tests.blob_images import disc_image

BACKGROUND = 12


def scattered_discs(rng: np.random.Generator, count: int, shape: tuple[int, int]) -> list[tuple[float, float, float]]:
    """``count`` discs (x, y, radius) on a grid, jittered by subpixel amounts, radii 1.5 to 8 px."""
    height, width = shape
    columns = int(math.ceil(math.sqrt(count * width / height)))
    step = width / columns
    return [((k % columns + 0.5) * step + rng.uniform(-3, 3), (k // columns + 0.5) * step + rng.uniform(-3, 3),
             rng.uniform(1.5, min(8.0, step / 3))) for k in range(count)]


def nearest(blobs: Blobs, point: tuple[float, float]) -> int:
    return int(np.argmin(np.linalg.norm(blobs.centroids - np.asarray(point), axis=1)))


def test_isolated_discs_are_found_unflagged_with_subpixel_centroids():
    rng = np.random.default_rng(5)
    discs = scattered_discs(rng, 20, (480, 640))
    blobs = detect_ir_blobs(disc_image(discs, (480, 640), BACKGROUND))
    assert len(blobs) == len(discs) and not blobs.flags.any()
    errors, radius_errors = [], []
    for x, y, radius in discs:
        k = nearest(blobs, (x, y))
        errors.append(np.hypot(*(blobs.centroids[k] - (x, y))))
        radius_errors.append(blobs.radius[k] - radius)
    assert np.sqrt(np.mean(np.square(errors))) < 0.02 and max(errors) < 0.05
    assert np.all(np.abs(radius_errors) < 0.5)
    assert np.all((blobs.quality > 0.85) & (blobs.quality <= 1.0))
    assert np.all(blobs.circularity > 0.75)


def test_noise_keeps_centroids_within_a_twentieth_of_a_pixel():
    rng = np.random.default_rng(6)
    discs = scattered_discs(rng, 20, (480, 640))
    image = disc_image(discs, (480, 640), BACKGROUND).astype(np.float64) + rng.normal(0.0, 3.0, (480, 640))
    blobs = detect_ir_blobs(np.clip(image, 0, 255).astype(np.uint8))
    assert len(blobs) == len(discs)
    errors = [np.hypot(*(blobs.centroids[nearest(blobs, (x, y))] - (x, y))) for x, y, _ in discs]
    assert np.sqrt(np.mean(np.square(errors))) < 0.05


def test_components_and_weighted_centroids_match_opencv_components_and_a_numpy_weighted_mean():
    rng = np.random.default_rng(7)
    image = disc_image(scattered_discs(rng, 20, (480, 640)), (480, 640), BACKGROUND)
    params = IrBlobParams(background=BACKGROUND)
    blobs = detect_ir_blobs(image, params)
    count, labels, stats, centres = cv2.connectedComponentsWithStats((image > params.threshold).astype(np.uint8))
    assert len(blobs) == count - 1
    weights = np.maximum(image.astype(np.float64) - BACKGROUND, 0.0)
    ys, xs = np.indices(image.shape)
    for label in range(1, count):
        k = nearest(blobs, centres[label])
        assert blobs.area[k] == stats[label, cv2.CC_STAT_AREA]
        component = labels == label
        rim = cv2.dilate(component.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
        w = weights * (rim & (component | (labels == 0)))
        expected = np.array([(w * xs).sum(), (w * ys).sum()]) / w.sum()
        np.testing.assert_allclose(blobs.centroids[k], expected, atol=1e-4)


@pytest.mark.parametrize("radius", [2.2, 3.0, 5.0])
def test_overlapping_discs_are_flagged_merged_when_apart_and_flagged_at_all_when_closer(radius):
    rng = np.random.default_rng(int(radius * 10))
    for _ in range(12):
        centre, angle = rng.uniform(50, 70, 2), rng.uniform(0, np.pi)
        for separation, expected in ((rng.uniform(1.3, 1.9), BlobFlag.MERGED),
                                     (rng.uniform(0.6, 1.3), BlobFlag.MERGED | BlobFlag.OCCLUDED)):
            other = centre + separation * radius * np.array([np.cos(angle), np.sin(angle)])
            found = detect_ir_blobs(disc_image([(*centre, radius), (*other, radius)], background=BACKGROUND))
            blobs = found.select(~found.flagged(BlobFlag.SPLIT))
            assert len(blobs) == 1 and blobs.flags[0] & expected, (separation, blobs.flags)
            assert blobs.quality[0] < 0.85


def test_a_cut_disc_is_occluded_not_merged():
    rng = np.random.default_rng(8)
    for radius in (3.0, 5.0, 8.0):
        x, y = rng.uniform(50, 70, 2)
        image = disc_image([(x, y, radius)], background=BACKGROUND)
        image[:, : int(x)] = BACKGROUND
        blobs = detect_ir_blobs(image)
        assert len(blobs) == 1 and blobs.flags[0] == BlobFlag.OCCLUDED


def test_a_disc_over_the_border_is_clipped():
    blobs = detect_ir_blobs(disc_image([(1.0, 60.0, 4.0), (80.0, 60.0, 4.0)], background=BACKGROUND))
    assert len(blobs) == 2
    assert blobs.flagged(BlobFlag.CLIPPED)[nearest(blobs, (1.0, 60.0))]
    assert blobs.clean().centroids[0] == pytest.approx((80.0, 60.0), abs=0.02)


def test_filters_drop_small_large_and_streaky_components():
    image = disc_image([(30.0, 30.0, 0.7), (80.0, 30.0, 4.0), (80.0, 80.0, 12.0)], background=BACKGROUND)
    cv2.line(image, (10, 100), (60, 100), 240, 1)
    blobs = detect_ir_blobs(image, IrBlobParams(max_radius=10.0), ShapeParams(min_area=3, min_circularity=0.3))
    assert len(blobs) == 1 and blobs.centroids[0] == pytest.approx((80.0, 30.0), abs=0.02)
    assert len(detect_ir_blobs(image, shape=ShapeParams(min_circularity=0.0))) == 3


def test_mono16_images_give_the_same_blobs_at_the_same_threshold_scale():
    image = disc_image([(40.3, 50.6, 3.0), (100.2, 60.1, 5.0)], background=BACKGROUND)
    eight = detect_ir_blobs(image)
    sixteen = detect_ir_blobs(image.astype(np.uint16) * 256, IrBlobParams(threshold=60.0 * 256))
    np.testing.assert_allclose(sixteen.centroids, eight.centroids, atol=1e-3)
    np.testing.assert_array_equal(sixteen.area, eight.area)


def test_an_empty_image_gives_no_blobs():
    blobs = detect_ir_blobs(np.full((48, 64), BACKGROUND, np.uint8))
    assert len(blobs) == 0 and blobs.centroids.shape == (0, 2)


def test_bad_input_is_refused_with_a_reason():
    with pytest.raises(ValueError, match="mono8 or mono16"):
        detect_ir_blobs(np.zeros((48, 64, 3), np.uint8))
    with pytest.raises(ValueError, match="min_roundness"):
        ShapeParams(min_roundness=1.5)
    with pytest.raises(ValueError, match="area range"):
        ShapeParams(min_area=50, max_area=10)
    with pytest.raises(ValueError, match="radius range"):
        IrBlobParams(min_radius=5, max_radius=2)
    with pytest.raises(ValueError, match=r"radius must have shape \(2,\), got \(3,\)"):
        Blobs(np.zeros((2, 2)), np.zeros(2), np.zeros(3), np.zeros(2), np.zeros(2), np.zeros(2), np.zeros(2, np.uint8))
