"""Corners from lines fitted to a quad's sides: on anti-aliased, blurred quads rendered at subpixel
positions with exact corners, against cv2.cornerSubPix on the same images; on small markers (a dark
border around a light inside) blurred so much that no profile reaches its plateaus, started where
cv2.cornerSubPix leaves them, 0.3 px inside: no side measured more than 0.05 px too large or too
small on average; the batch line fit against cv2.fitLine."""

import cv2
import numpy as np
import pytest

from services.detection.markers.corner_lines import fit_lines, refine_corners

SIZE = 120
SUPERSAMPLE = 8
BLUR_SIGMA_PX = 0.8
START_NOISE_PX = 0.4
MAX_ERROR_PX = 0.08
"""Bound on every refined corner's error on the clean renders (exact corners known to float precision)."""


def coverage(corners: np.ndarray) -> np.ndarray:
    """(SIZE, SIZE) float: the share of each pixel inside the convex quad ``corners`` (4, 2) px (pixel centres
    at integers), from SUPERSAMPLE^2 point samples."""
    fine = (np.arange(SIZE * SUPERSAMPLE) + 0.5) / SUPERSAMPLE - 0.5
    x, y = np.meshgrid(fine, fine)
    (ax, ay), (bx, by) = corners[1] - corners[0], corners[2] - corners[1]
    sign = np.sign(ax * by - ay * bx)
    inside = np.ones(x.shape, bool)
    for a, b in zip(corners, np.roll(corners, -1, axis=0), strict=True):
        inside &= sign * ((b[0] - a[0]) * (y - a[1]) - (b[1] - a[1]) * (x - a[0])) >= 0
    return inside.reshape(SIZE, SUPERSAMPLE, SIZE, SUPERSAMPLE).mean(axis=(1, 3))


def render_quad(corners: np.ndarray, dark: float = 30.0, light: float = 220.0, border: float = 0.0,
                blur_px: float = BLUR_SIGMA_PX) -> np.ndarray:
    """(SIZE, SIZE) uint8: the convex quad ``corners`` (4, 2) px filled with ``dark`` on ``light``, each pixel
    its area average; with ``border`` > 0 only a frame of that share of the side is dark, the quad inside
    it light (a marker's black border and white bits), then blurred by ``blur_px``."""
    shade = coverage(corners)
    if border > 0:
        centre = corners.mean(axis=0)
        shade -= coverage(centre + (1 - 2 * border) * (corners - centre))
    image = light + (dark - light) * shade
    return np.clip(np.round(cv2.GaussianBlur(image, (0, 0), blur_px)), 0, 255).astype(np.uint8)


def random_quad(rng: np.random.Generator) -> np.ndarray:
    """(4, 2) a square of side 40-70 px, turned, skewed a little by perspective, clockwise in the image."""
    side, angle = rng.uniform(40, 70), rng.uniform(0, np.pi / 2)
    square = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) * side / 2
    turned = square @ np.array([[np.cos(angle), np.sin(angle)], [-np.sin(angle), np.cos(angle)]])
    skewed = turned * (1 + 0.1 * rng.uniform(-1, 1, (4, 1)))
    return skewed + SIZE / 2 + rng.uniform(-3, 3, 2)


def sub_pix(image: np.ndarray, start: np.ndarray) -> np.ndarray:
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 30, 0.01)
    return cv2.cornerSubPix(image, start.astype(np.float32).copy(), (5, 5), (-1, -1), criteria)


def test_corners_land_on_the_true_ones_and_closer_than_corner_sub_pix():
    rng = np.random.default_rng(3)
    ours, theirs = [], []
    for _ in range(12):
        truth = random_quad(rng)
        image = render_quad(truth)
        start = truth + rng.normal(0, START_NOISE_PX, truth.shape)
        refined = refine_corners(image, start[None], 2.0, iterations=2)[0]
        ours.append(np.linalg.norm(refined - truth, axis=1))
        theirs.append(np.linalg.norm(sub_pix(image, start) - truth, axis=1))
    ours, theirs = np.concatenate(ours), np.concatenate(theirs)
    assert ours.max() < MAX_ERROR_PX
    assert np.median(ours) < 0.25 * np.median(theirs)
    assert np.mean(ours) < np.mean(theirs)


def outward_offsets(corners: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """(4,) per side of ``truth`` (4, 2, clockwise in the image): the mean offset of ``corners`` along its outward
    normal, px (positive: the quad measured too large)."""
    side = np.roll(truth, -1, axis=0) - truth
    outward = np.stack([side[:, 1], -side[:, 0]], axis=1) / np.linalg.norm(side, axis=1)[:, None]
    error = corners - truth
    return np.sum(0.5 * (error + np.roll(error, -1, axis=0)) * outward, axis=1)


def small_blurred_markers(count: int) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """``(truth, image, start)``: quads of side 30-45 px with a dark border of an eighth of the side around a
    light inside (an 8-cell marker at 4-6 px a cell), blurred by 1.2 px, the start corners 0.3 px inside the
    true ones (as cv2.cornerSubPix leaves them) plus noise."""
    rng = np.random.default_rng(17)
    cases = []
    for _ in range(count):
        side, angle = rng.uniform(30, 45), rng.uniform(0, np.pi / 2)
        square = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) * side / 2
        truth = square @ np.array([[np.cos(angle), np.sin(angle)], [-np.sin(angle), np.cos(angle)]])
        truth = truth + SIZE / 2 + rng.uniform(-3, 3, 2)
        centre = truth.mean(axis=0)
        start = truth - 0.3 * np.sqrt(2) * (truth - centre) / np.linalg.norm(truth - centre, axis=1)[:, None]
        cases.append((truth, render_quad(truth, border=0.125, blur_px=1.2), start + rng.normal(0, 0.05, (4, 2))))
    return cases


def test_small_blurred_markers_are_measured_neither_too_small_nor_too_large():
    offsets = []
    for truth, image, start in small_blurred_markers(12):
        search = 0.4 * np.linalg.norm(truth[1] - truth[0]) / 8
        refined = refine_corners(image, start[None], search, level_px=0.5 * search / 0.4)[0]
        assert np.abs(refined - truth).max() < 2 * MAX_ERROR_PX
        offsets.append(outward_offsets(refined, truth))
    assert abs(np.mean(offsets)) < 0.05 and np.abs(np.mean(offsets, axis=0)).max() < 0.05


def test_light_quads_on_dark_and_several_at_once():
    rng = np.random.default_rng(5)
    truths = np.array([random_quad(rng) for _ in range(3)])
    images = [render_quad(truth, dark=200.0, light=40.0) for truth in truths]
    starts = truths + rng.normal(0, START_NOISE_PX, truths.shape)
    refined = np.array([refine_corners(image, starts[n:n + 1], 2.0, iterations=2)[0] for n, image in enumerate(images)])
    assert np.abs(refined - truths).max() < MAX_ERROR_PX
    together = refine_corners(images[0], starts, np.array([2.0, 1.5, 2.5]), iterations=2)
    assert together.shape == (3, 4, 2) and together.dtype == np.float32
    assert np.abs(together[0] - refined[0]).max() < 1e-4


def test_a_quad_without_edges_keeps_its_corners():
    start = np.array([[[30.0, 30.0], [80.0, 30.0], [80.0, 80.0], [30.0, 80.0]]])
    assert np.array_equal(refine_corners(np.full((SIZE, SIZE), 128, np.uint8), start), start.astype(np.float32))
    assert refine_corners(np.zeros((SIZE, SIZE), np.uint8), np.zeros((0, 4, 2))).shape == (0, 4, 2)


@pytest.mark.parametrize(("image", "corners", "message"), [
    (np.zeros((10, 10), np.uint8), np.zeros((1, 3, 2)), r"corners must have shape \(N, 4, 2\), got \(1, 3, 2\)"),
    (np.zeros((10, 10, 3), np.uint8), np.zeros((1, 4, 2)), r"image must have shape \(H, W\), got \(10, 10, 3\)"),
    (np.zeros((10, 10), np.uint8), np.full((1, 4, 2), np.nan), "corners must be finite"),
])
def test_bad_shapes_are_named(image, corners, message):
    with pytest.raises(ValueError, match=message):
        refine_corners(image, corners)


def noisy_lines(rng: np.random.Generator, outliers: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """20 lines of 40 points each, 0.05 px noise across, ``outliers`` of each moved 2-5 px off:
    (20, 40, 2) points, (20, 40) valid mask (90 %), (20, 3) true lines (a, b, c), a^2 + b^2 = 1."""
    points, valid, truth = [], [], []
    for _ in range(20):
        angle, offset = rng.uniform(0, np.pi), rng.uniform(-50, 50, 2)
        normal = np.array([-np.sin(angle), np.cos(angle)])
        line = offset + rng.uniform(-30, 30, 40)[:, None] * [np.cos(angle), np.sin(angle)]
        line += rng.normal(0, 0.05, (40, 1)) * normal
        line[:outliers] += rng.uniform(2, 5, (outliers, 1)) * normal
        points.append(line)
        valid.append(rng.random(40) > 0.1)
        truth.append([*normal, -normal @ offset])
    return np.array(points), np.array(valid), np.array(truth)


def line_gap(line: np.ndarray, other: np.ndarray, points: np.ndarray) -> float:
    """Largest distance from ``line`` (a, b, c) to the points of ``other`` nearest ``points`` (M, 2)."""
    on_other = points - np.outer(points @ other[:2] + other[2], other[:2])
    return float(np.abs(on_other @ line[:2] + line[2]).max())


def cv_line(points: np.ndarray, distance: int) -> np.ndarray:
    vx, vy, x0, y0 = cv2.fitLine(points.astype(np.float32), distance, 0, 0.01, 0.01).ravel()
    return np.array([vy, -vx, vx * y0 - vy * x0])


def test_the_batch_line_fit_matches_cv2_fit_line_without_outliers():
    points, valid, _ = noisy_lines(np.random.default_rng(11), outliers=0)
    plain, robust = fit_lines(points, valid, iterations=0), fit_lines(points, valid)
    assert np.allclose(np.hypot(robust[:, 0], robust[:, 1]), 1.0)
    for n in range(len(points)):
        used = points[n][valid[n]]
        reference = cv_line(used, cv2.DIST_L2)
        assert line_gap(plain[n], reference, used) < 1e-3
        assert line_gap(robust[n], reference, used) < 0.03
    assert np.isnan(fit_lines(points[:1], np.zeros((1, 40), bool))).all()


def test_the_batch_line_fit_resists_outliers_as_well_as_cv2_fit_line():
    points, valid, truth = noisy_lines(np.random.default_rng(12), outliers=4)
    lines = fit_lines(points, valid)
    ours = [line_gap(lines[n], truth[n], points[n][valid[n]]) for n in range(len(points))]
    theirs = [line_gap(cv_line(points[n][valid[n]], cv2.DIST_HUBER), truth[n], points[n][valid[n]])
              for n in range(len(points))]
    assert max(ours) < 0.06 and np.median(ours) <= np.median(theirs)
    plain = fit_lines(points, valid, iterations=0)
    assert np.median(ours) < 0.25 * np.median([line_gap(plain[n], truth[n], points[n]) for n in range(len(points))])


def test_with_the_calibration_corners_of_a_quad_bent_by_distortion_land_on_the_true_ones():
    K = np.array([[150.0, 0.0, 20.0], [0.0, 150.0, 15.0], [0.0, 0.0, 1.0]])
    dist = np.array([-0.35, 0.12, 0.0, 0.0, 0.0])
    truth_undistorted = np.array([[45.0, 40.3], [95.4, 42.0], [93.8, 93.1], [44.2, 91.7]])
    straight = render_quad(truth_undistorted).astype(np.float32)
    u, v = np.meshgrid(np.arange(SIZE, dtype=np.float64), np.arange(SIZE, dtype=np.float64))
    source = cv2.undistortPoints(np.stack([u.ravel(), v.ravel()], axis=1).reshape(-1, 1, 2), K, dist, P=K,
                                 criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12))
    source = source.reshape(SIZE, SIZE, 2).astype(np.float32)
    bent = cv2.remap(straight, source[..., 0], source[..., 1], cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)
    rays = np.c_[truth_undistorted, np.ones(4)] @ np.linalg.inv(K).T
    truth = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), K, dist)[0].reshape(4, 2)
    start = truth + np.random.default_rng(2).normal(0, START_NOISE_PX, truth.shape)
    with_lens = refine_corners(bent, start[None], 2.0, iterations=2, K=K, dist=dist)[0]
    without = refine_corners(bent, start[None], 2.0, iterations=2)[0]
    assert np.abs(with_lens - truth).max() < MAX_ERROR_PX
    assert np.abs(without - truth).max() > 2 * np.abs(with_lens - truth).max()
    assert np.array_equal(refine_corners(bent, start[None], 2.0, K=K, dist=np.zeros(5)),
                          refine_corners(bent, start[None], 2.0))
