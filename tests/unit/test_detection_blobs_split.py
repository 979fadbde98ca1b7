"""Merged blobs split into two discs: on two anti-aliased discs run together at known sub-pixel centres, the two
SPLIT rows after the merged blob's own lie at the discs' centres, cross-checked against a plain reference (each
disc drawn alone, its plain weighted centroid); a round disc and a tiny blob are not split."""

import cv2
import numpy as np
import pytest
from scipy.optimize import least_squares

from services.detection.blobs.bright import BlobFlag, detect_ir_blobs, moment_shape
from services.detection.blobs.split import MAX_RMS, MIN_GAP_PX, split_two_discs
from tests.blob_images import disc_image

BACKGROUND = 12


def alone_centroid(x: float, y: float, radius: float) -> np.ndarray:
    """The plain intensity-weighted centroid of one disc drawn alone."""
    levels = disc_image([(x, y, radius)], background=BACKGROUND).astype(np.float64) - BACKGROUND
    ys, xs = np.mgrid[0:levels.shape[0], 0:levels.shape[1]]
    return np.array([(levels * xs).sum(), (levels * ys).sum()]) / levels.sum()


@pytest.mark.parametrize("seed", range(4))
def test_two_merged_discs_split_at_their_centres(seed):
    rng = np.random.default_rng(seed)
    split = 0
    for _ in range(10):
        radii = rng.uniform(2.5, 6.0, 2)
        centre, angle = rng.uniform(70, 90, 2), rng.uniform(0, np.pi)
        gap = rng.uniform(0.7, 0.95) * radii.sum()
        direction = np.array([np.cos(angle), np.sin(angle)])
        truth = np.array([centre, centre + gap * direction])
        blobs = detect_ir_blobs(disc_image([(*truth[0], radii[0]), (*truth[1], radii[1])], (160, 160), BACKGROUND))
        parts = blobs.flagged(BlobFlag.SPLIT)
        assert len(blobs) in (1, 3) and not blobs.flagged(BlobFlag.SPLIT)[0]
        assert blobs.flags[0] & (BlobFlag.MERGED | BlobFlag.OCCLUDED)
        if not parts.any():
            continue
        split += 1
        assert parts.tolist() == [False, True, True]
        found = blobs.centroids[1:]
        if np.linalg.norm(found[0] - truth[0]) > np.linalg.norm(found[0] - truth[1]):
            found = found[::-1]
        reference = np.array([alone_centroid(*truth[k], radii[k]) for k in range(2)])
        np.testing.assert_allclose(reference, truth, atol=0.02)
        assert np.abs(found - truth).max() < 0.1, (radii, gap)
        assert np.abs(found - reference).max() < 0.1, (radii, gap)
    assert split >= 8


def test_a_round_disc_and_a_tiny_blob_are_not_split():
    image = disc_image([(40.3, 50.6, 5.0), (100.0, 60.0, 1.0)], background=BACKGROUND)
    assert not detect_ir_blobs(image).flagged(BlobFlag.SPLIT).any()
    weights = np.zeros((5, 5), np.float32)
    weights[1:3, 1:3] = 100.0
    assert split_two_discs(weights, (1.5, 1.5), (1.0, 0.0)) is None


def test_a_split_blob_keeps_its_own_row_for_those_who_take_clean_blobs():
    image = disc_image([(60.2, 60.7, 4.0), (66.1, 61.9, 4.0), (20.0, 20.0, 4.0)], background=BACKGROUND)
    blobs = detect_ir_blobs(image)
    assert blobs.flagged(BlobFlag.SPLIT).sum() == 2
    assert len(blobs.clean()) == 1
    np.testing.assert_allclose(blobs.clean().centroids[0], (20.0, 20.0), atol=0.02)


def merged_window(truth: np.ndarray, radii: np.ndarray) -> tuple[np.ndarray, tuple[float, float], tuple[float, float]]:
    """Two discs ``truth`` (2, 2) px of ``radii`` (2,) rendered together: their weights above the background, the
    weighted centroid and the major axis (``bright.moment_shape``), as the detector hands them to the split."""
    weights = np.maximum(disc_image([(*truth[0], radii[0]), (*truth[1], radii[1])], (40, 40), BACKGROUND)
                         .astype(np.float32) - BACKGROUND, 0.0)
    centroid, axis, _ = moment_shape(cv2.moments(weights))
    return weights, centroid, axis


def two_disc_cases(count: int, smallest: float, largest: float, seed: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """``count`` pairs (truth (2, 2) px, radii (2,) px) of discs run together, radii in [smallest, largest]."""
    rng = np.random.default_rng(seed)
    cases = []
    for _ in range(count):
        radii = rng.uniform(smallest, largest, 2)
        angle = rng.uniform(0, np.pi)
        gap = rng.uniform(0.7, 0.95) * radii.sum()
        centre = rng.uniform(15, 17, 2)
        cases.append((np.array([centre, centre + gap * np.array([np.cos(angle), np.sin(angle)])]), radii))
    return cases


def reference_split(weights: np.ndarray, centroid: tuple[float, float], axis: tuple[float, float]
                    ) -> np.ndarray | None:
    """The two discs' centres (2, 2) px as scipy's Levenberg-Marquardt fits the split's model to every pixel of
    the bounding box of ``weights``, started by four rounds of two means along ``axis`` (each lit pixel to the
    nearer mean), or None where the split's rules refuse the fit (residual RMS above ``MAX_RMS`` of the peak,
    centres nearer than ``MIN_GAP_PX``)."""
    rows, columns = np.nonzero(weights)
    mass = weights[rows, columns].astype(np.float64)
    along = (columns - centroid[0]) * axis[0] + (rows - centroid[1]) * axis[1]
    ends = [-1.0, 1.0]
    for _ in range(4):
        second = np.abs(along - ends[1]) < np.abs(along - ends[0])
        ends = [np.average(along[~second], weights=mass[~second]), np.average(along[second], weights=mass[second])]
    shares = [mass[~second].sum() / mass.max(), mass[second].sum() / mass.max()]
    start = [centroid[0] + ends[0] * axis[0], centroid[1] + ends[0] * axis[1], centroid[0] + ends[1] * axis[0],
             centroid[1] + ends[1] * axis[1], np.sqrt(shares[0] / np.pi), np.sqrt(shares[1] / np.pi), mass.max()]
    ys, xs = np.mgrid[rows.min():rows.max() + 1, columns.min():columns.max() + 1]
    values = weights[ys, xs].astype(np.float64)

    def residuals(params: np.ndarray) -> np.ndarray:
        reach = [params[4 + k] + 0.5 - np.hypot(xs - params[2 * k], ys - params[2 * k + 1]) for k in range(2)]
        return (params[6] * np.clip(np.maximum(*reach), 0.0, 1.0) - values).ravel()

    fit = least_squares(residuals, start, method="lm")
    rms = np.sqrt(np.mean(fit.fun**2)) / fit.x[6]
    centres = fit.x[:4].reshape(2, 2)
    return centres if rms <= MAX_RMS and np.linalg.norm(centres[0] - centres[1]) >= MIN_GAP_PX else None


@pytest.mark.parametrize(("smallest", "largest"), [(2.5, 6.0), (1.2, 2.5)])
def test_the_split_matches_scipy_least_squares(smallest, largest):
    """Both keep the fit or both refuse it; where kept, the same centres as scipy's to 0.01 px (or nearer
    the true ones)."""
    agreed = 0
    for truth, radii in two_disc_cases(60, smallest, largest, 7):
        weights, centroid, axis = merged_window(truth, radii)
        found = split_two_discs(weights, centroid, axis)
        reference = reference_split(weights, centroid, axis)
        assert (found is None) == (reference is None)
        if found is None or reference is None:
            continue
        nearer = np.abs(found.centres - truth).max() <= np.abs(reference - truth).max()
        assert np.abs(found.centres - reference).max() <= 0.01 or nearer
        agreed += 1
    assert agreed >= 50
