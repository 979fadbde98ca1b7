"""Scale-space (LoG) blobs on anti-aliased discs of known centre and radius, cross-checked against
``cv2.SimpleBlobDetector`` on the same images; the overlap of two discs against OpenCV's polygon
intersection."""

import math

import cv2
import numpy as np
import pytest

from services.detection.blobs.bright import BlobFlag
from services.detection.blobs.scale_space import LogBlobParams, detect_log_blobs, disc_overlap
from tests.blob_images import disc_image

SHAPE = (240, 320)


def disc_grid(seed: int) -> list[tuple[float, float, float]]:
    """12 discs (x, y, radius px), radii 3 to 12 px, on a jittered 4 x 3 grid."""
    rng = np.random.default_rng(seed)
    return [(40.0 + 78.0 * (k % 4) + rng.uniform(-4, 4), 45.0 + 75.0 * (k // 4) + rng.uniform(-4, 4),
             rng.uniform(3.0, 12.0)) for k in range(12)]


def simple_blob_detector(image: np.ndarray, bright: bool) -> np.ndarray:
    """(N, 3) x, y, radius (half the keypoint size) of ``cv2.SimpleBlobDetector``'s blobs."""
    params = cv2.SimpleBlobDetector_Params()
    params.blobColor = 255 if bright else 0
    params.minArea, params.maxArea = 10.0, 5000.0
    params.filterByInertia = params.filterByConvexity = False
    return np.array([(*k.pt, k.size / 2.0) for k in cv2.SimpleBlobDetector_create(params).detect(image)])


def match(found: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """(len(truth),) index of the nearest found row per truth row; the pairing must be one to one."""
    nearest = np.argmin(np.linalg.norm(found[None, :, :2] - truth[:, None, :2], axis=2), axis=1)
    assert len(set(nearest.tolist())) == len(truth)
    return nearest


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_discs_are_found_once_at_their_centre_with_their_radius(seed):
    truth = np.array(disc_grid(seed))
    blobs = detect_log_blobs(disc_image(truth, SHAPE, 30, 220))
    assert len(blobs) == len(truth)
    found = np.column_stack([blobs.centroids, blobs.radius])[match(np.column_stack([blobs.centroids,
                                                                                    blobs.radius]), truth)]
    assert np.max(np.linalg.norm(found[:, :2] - truth[:, :2], axis=1)) < 0.1
    assert np.max(np.abs(found[:, 2] - truth[:, 2]) / truth[:, 2]) < 0.05
    assert blobs.quality == pytest.approx(190 / 255, abs=0.06)
    assert not blobs.flags.any() and np.isnan(blobs.circularity).all()


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_same_blobs_as_opencv_simple_blob_detector_within_a_pixel(seed):
    image = disc_image(disc_grid(seed), SHAPE, 30, 220)
    blobs = detect_log_blobs(image)
    ours = np.column_stack([blobs.centroids, blobs.radius])
    opencv = simple_blob_detector(image, bright=True)
    assert len(opencv) == len(ours)
    paired = ours[match(ours, opencv)]
    assert np.max(np.linalg.norm(paired[:, :2] - opencv[:, :2], axis=1)) < 1.0
    assert np.max(np.abs(paired[:, 2] - opencv[:, 2])) < 1.0


def test_polarity_picks_bright_dark_or_both():
    bright = [(60.0, 60.0, 6.0), (200.0, 150.0, 9.0)]
    dark = [(150.0, 60.0, 5.0)]
    image = disc_image(bright, SHAPE, 120, 230) - (disc_image(dark, SHAPE, 0, 100))
    for polarity, expected in (("bright", bright), ("dark", dark), ("both", bright + dark)):
        blobs = detect_log_blobs(image, LogBlobParams(polarity=polarity))
        assert len(blobs) == len(expected), polarity
        truth = np.array(expected)
        paired = blobs.centroids[match(blobs.centroids, truth)]
        np.testing.assert_allclose(paired, truth[:, :2], atol=0.1)
    opencv = simple_blob_detector(image, bright=False)
    assert len(opencv) == 1 and opencv[0, :2] == pytest.approx(dark[0][:2], abs=1.0)


def test_a_disc_over_the_border_is_clipped():
    blobs = detect_log_blobs(disc_image([(3.0, 100.0, 8.0), (150.0, 100.0, 8.0)], SHAPE, 30, 220))
    assert len(blobs) == 2
    clipped = blobs.flagged(BlobFlag.CLIPPED)
    assert clipped.sum() == 1 and blobs.centroids[clipped][0, 0] < 10


@pytest.mark.parametrize(("distance", "r1", "r2"), [(3.0, 5.0, 5.0), (7.0, 4.0, 6.0), (2.0, 8.0, 3.0),
                                                    (9.5, 4.0, 6.0), (12.0, 4.0, 6.0)])
def test_disc_overlap_matches_opencv_polygon_intersection(distance, r1, r2):
    scale = 1000.0
    first, second = (cv2.ellipse2Poly((int(x * scale), 0), (int(r * scale), int(r * scale)), 0, 0, 360, 1)[:-1]
                     for x, r in ((0.0, r1), (distance, r2)))  # the last point repeats the first: dropped
    shared, _ = cv2.intersectConvexConvex(first.astype(np.float32), second.astype(np.float32))
    expected = shared / scale**2 / (math.pi * min(r1, r2) ** 2)
    assert disc_overlap(distance, r1, r2) == pytest.approx(expected, abs=2e-3)


def test_bad_settings_are_refused_with_a_reason():
    with pytest.raises(ValueError, match="min_sigma"):
        LogBlobParams(min_sigma=5.0, max_sigma=2.0)
    with pytest.raises(ValueError, match="polarity"):
        LogBlobParams(polarity="grey")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="mono8, mono16 or bgr8"):
        detect_log_blobs(np.zeros((10, 10), np.float32))
