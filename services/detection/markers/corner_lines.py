"""Marker corners as the intersections of straight lines fitted to the quad's four sides.

Each side of a detected quad is sampled at ``SAMPLES`` points along its middle (clear of the
corners, where the neighbouring side's edge blurs into the profile). At each point the image is
read along the side's normal (``cv2.remap``, bicubic): a profile of ``2 * STEPS + 1`` evenly
spaced samples ``search_px`` either way, and two level samples ``level_px`` either way, the
middle of the marker's dark border inside and the white margin outside. The edge is located in
three steps:

1. a first edge per side, where the side's mean profile crosses the mean of its levels; as the
   input edge may sit a few tenths of a pixel off (OpenCV's subpixel corners sit inside), the
   levels are then read again ``level_px`` either side of that edge, so that neither reads
   further into the edge's blur than the other;
2. per point, where its profile crosses the midpoint of its two levels (linear between samples);
3. per point, the edge a sharp step of the same area would have over a window centred on that
   crossing (1 px either way, or as far as the profile reaches, but at least a quarter of its
   span), the profile scaled from its inside level (0) to its outside one (1).

A blur symmetric about the edge moves neither the midpoint nor the area of a window centred on
the edge, whatever its width, and levels read away from the profile's ends are the plateaus the
window's ends may not reach (a profile normalised by its own ends is pulled towards the window's
centre, which made small, blurred markers measure too small). The area, unlike the crossing of
interpolated samples, has no preference for pixel centres on sharp edges (on axis-aligned sides
every sample of a side has the same phase). Light bits next to the dark border lift its level
once the blur's sigma nears a quarter of a cell, which moves the edge outwards by a few
hundredths of a pixel.

The sign of the edge (dark inside for ordinary markers, light inside for inverted ones) comes
from each marker's mean contrast, so both polarities work. A line is fitted to each side's edge
points by total least squares with Tukey's biweight (``fit_lines``:
points off the edge, from glare or a neighbouring bit, lose their weight), and adjacent sides'
lines meet in the corners.

Corner detectors that look at the corner's own neighbourhood (``cv2.cornerSubPix``) drift
inwards as blur rounds the corner; lines fitted to the sides away from it do not.

Lens distortion: the edges are always searched in the image as it is, along the straight
sides of the input quad (a side bent by distortion stays well within the search window). Without
a calibration the lines are fitted there too, which holds on short sides near the image centre;
with one (``K``, ``dist``) the edge points are undistorted first, the lines fitted and
intersected in undistorted pixels, and the corners distorted back. A marker whose sides cannot
all be measured (too few edge points, an edge outside the search window,
lines that do not meet near the input corners) keeps its input corners.
"""

from __future__ import annotations

import cv2
import numpy as np

from services.geometry.camera import UNDISTORT_CRITERIA, project_points
from services.geometry.shapes import check_shape

__all__ = ["SAMPLES", "STEPS", "fit_lines", "refine_corners"]

SAMPLES = 32
"""Edge points sampled per side."""
STEPS = 8
"""Profile samples on each side of the input edge along its normal (``2 * STEPS + 1`` in all)."""
END_MARGIN = 0.12
"""Fraction of a side left out at each end, at least ``2 * search_px`` px."""
MIN_POINTS = 0.4
"""Share of a side's samples that must give an edge point."""
MIN_CONTRAST = 0.3
"""An edge point's contrast must reach this fraction of its side's median contrast."""
TUKEY_K = 4.685
"""Tukey's biweight cut-off in robust standard deviations of the residuals (95 % efficiency for Gaussian noise)."""
REWEIGHTS = 2
"""Reweighted refits of each side's line after the first, unweighted one."""
MIN_SCALE_PX = 0.01
"""Floor of the robust residual scale, px."""
LEVEL_REACH = 1.25
"""Default ``level_px``, in ``search_px``."""


def refine_corners(image: np.ndarray, corners: np.ndarray, search_px: float | np.ndarray = 2.0,
                   iterations: int = 1, K: np.ndarray | None = None, dist: np.ndarray | None = None,
                   level_px: float | np.ndarray | None = None) -> np.ndarray:
    """Corners of quads in ``image`` refined to the intersections of lines fitted to their sides.

    ``image``: (H, W) uint8 or float grey; ``corners``: (N, 4, 2) float px (centre of the top-left
    pixel at (0, 0)), in order around each quad (ArUco's TL, TR, BR, BL); ``search_px``: how far
    from each input side its edge is looked for along the normal, one number or (N,) per quad;
    keep it below half the width of the quad's dark border so inner edges stay out of reach.
    ``level_px``: how far from each side its dark and light levels are read, one number or (N,)
    per quad (default ``LEVEL_REACH * search_px``); at most half the dark border's width, so the
    inside level is the border's, not a bit's.
    ``iterations``: refinement passes, each starting from the previous one's corners (one is enough
    from cornerSubPix's corners; rougher starts gain from a second). ``K`` (3, 3) and ``dist``
    (OpenCV distortion coefficients), when both are given and ``dist`` is not all zero: the edge
    points are undistorted before the lines are fitted and the corners distorted back, so sides
    that distortion bends still meet where they should. Returns (N, 4, 2) float32 px of
    ``image``; a quad that cannot be refined keeps its input.
    """
    corners = check_shape(corners, "N,4,2", "corners", np.float64)
    if not np.isfinite(corners).all():
        raise ValueError("corners must be finite")
    image = check_shape(image, "H,W", "image")
    search = np.broadcast_to(np.asarray(search_px, dtype=np.float64), (len(corners),)).copy()
    level = search * LEVEL_REACH if level_px is None else \
        np.broadcast_to(np.asarray(level_px, dtype=np.float64), (len(corners),)).copy()
    if len(corners) == 0:
        return corners.astype(np.float32)
    reach = max(search.max() * (iterations + 1), level.max() + search.max() * iterations) + 4.0
    low = np.clip(np.floor(corners.min(axis=(0, 1)) - reach), 0, None).astype(int)
    high = np.clip(np.ceil(corners.max(axis=(0, 1)) + reach), 0, image.shape[::-1]).astype(int)
    grey = image[low[1]:high[1], low[0]:high[0]].astype(np.float32)
    if grey.size == 0:
        return corners.astype(np.float32)
    current = corners - low
    lens = None
    if K is not None and dist is not None and np.any(dist):
        lens = (np.asarray(K, dtype=np.float64), np.asarray(dist, dtype=np.float64).ravel())
    for _ in range(iterations):
        refined, ok = _refine_once(grey, current, search, level, low, lens)
        current[ok] = refined[ok]
    current += low
    moved = np.linalg.norm(current - corners, axis=2).max(axis=1)
    keep = np.isfinite(current).all(axis=(1, 2)) & (moved <= 2 * np.broadcast_to(search_px, moved.shape) + 1.0)
    return np.where(keep[:, None, None], current, corners).astype(np.float32)


def _refine_once(grey: np.ndarray, corners: np.ndarray, search: np.ndarray, level: np.ndarray, origin: np.ndarray,
                 lens: tuple[np.ndarray, np.ndarray] | None) -> tuple[np.ndarray, np.ndarray]:
    """One pass on ``grey``, the image window whose top-left pixel is ``origin`` (x, y): (N, 4, 2) refined
    corners (window px) and (N,) bool, whether each quad's four lines were found. ``lens``: (K, dist)
    to fit the lines in undistorted pixels, or None."""
    start = corners
    end = np.roll(corners, -1, axis=1)
    length = np.linalg.norm(end - start, axis=2)
    along = (end - start) / np.maximum(length, 1e-9)[..., None]
    normal = np.stack([along[..., 1], -along[..., 0]], axis=-1)  # outwards when the quad turns clockwise
    margin = np.maximum(END_MARGIN * length, 2 * search[:, None])
    spread = np.linspace(0.0, 1.0, SAMPLES)
    position = margin[..., None] + spread * (length - 2 * margin)[..., None]
    base = start[:, :, None, :] + position[..., None] * along[:, :, None, :]
    steps = np.linspace(-1.0, 1.0, 2 * STEPS + 1)[None, :] * search[:, None]
    samples = _sample(grey, base, normal, np.concatenate([-level[:, None], steps, level[:, None]], axis=1))
    profile = samples[..., 1:-1]
    contrast = samples[..., -1] - samples[..., 0]
    polarity = np.sign(contrast.sum(axis=(1, 2)))[:, None, None]
    strong = (contrast * polarity >= MIN_CONTRAST * np.median(np.abs(contrast), axis=2, keepdims=True)) \
        & (polarity != 0) & (length > 2 * margin + 2.0)[..., None]
    middle, found = _crossings(profile.mean(axis=2), 0.5 * (samples[..., 0] + samples[..., -1]).mean(axis=2),
                               polarity[..., 0], search[:, None])
    middle = np.where(found, middle, 0.0)
    levels = _sample(grey, base + middle[..., None, None] * normal[:, :, None, :], normal,
                     np.stack([-level, level], axis=1))
    crossing, found = _crossings(profile, levels.mean(axis=-1), polarity, search[:, None, None])
    offset = _centred_area_edges(profile, levels, crossing, search[:, None, None])
    edge = base + offset[..., None] * normal[:, :, None, :]
    valid = strong & found
    enough = valid.sum(axis=2) >= MIN_POINTS * SAMPLES
    if lens is not None:
        edge = undistort_pixels(edge + origin, *lens)
    lines = fit_lines(edge, valid)
    lines[~enough] = np.nan
    meet = np.cross(np.roll(lines, 1, axis=1), lines)
    ok = np.all(np.isfinite(meet), axis=(1, 2)) & (np.abs(meet[..., 2]) > 1e-9).all(axis=1)
    refined = meet[..., :2] / np.where(ok[:, None, None], meet[..., 2:], 1.0)
    if lens is not None:
        refined = distort_pixels(np.where(ok[:, None, None], refined, corners + origin), *lens) - origin
    return refined, ok


def _sample(grey: np.ndarray, points: np.ndarray, normal: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """(N, 4, S, M) float32 bicubic samples of ``grey`` at ``points`` (N, 4, S, 2) moved by ``offsets`` (N, M) px
    along their side's ``normal`` (N, 4, 2)."""
    x, y = ((points[..., None, i] + offsets[:, None, None, :] * normal[:, :, None, None, i]).astype(np.float32)
            for i in (0, 1))
    shape = (x.shape[0] * x.shape[1], x.shape[2] * x.shape[3])  # one row per side: few rows, little threading cost
    samples = cv2.remap(grey, x.reshape(shape), y.reshape(shape), cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)
    return samples.reshape(x.shape)


def _crossings(profile: np.ndarray, threshold: np.ndarray, polarity: np.ndarray,
               search: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where profiles (..., 2 * STEPS + 1), read outwards over ``-search .. search`` px, cross their
    ``threshold`` (...) towards the outside's level (``polarity``: +1 for a dark inside; it and ``search``
    broadcast to the profiles' leading shape): the offset (...) px along the normal, interpolated linearly
    between the two samples either side, and (...) bool, whether the profile crosses there (a profile that
    rises steadily crosses after as many samples as it has below the threshold)."""
    rising = (profile - threshold[..., None]) * polarity[..., None]
    k = np.minimum(np.maximum(np.count_nonzero(rising < 0, axis=-1) - 1, 0), profile.shape[-1] - 2)
    pair = _pick(rising, k[..., None] + np.arange(2))
    below, above = pair[..., 0], pair[..., 1]
    found = (below < 0) & (above >= 0)
    fraction = below / np.where(found, below - above, -1.0)
    return (k + fraction) * (search / STEPS) - search, found


def _centred_area_edges(profile: np.ndarray, levels: np.ndarray, centre: np.ndarray, search: np.ndarray) -> np.ndarray:
    """Edge offsets (N, 4, S) px from profiles (N, 4, S, 2 * STEPS + 1) read outwards over ``-search .. search``
    px (``search`` broadcast to (N, 4, S)), their inside and outside ``levels`` (N, 4, S, 2) and a first
    estimate ``centre`` (N, 4, S) of each edge: where a sharp step would have the same area under the
    profile, scaled to run from 0 (inside) to 1 (outside), as the profile has over a window centred on
    ``centre`` (half-width: 1 px, or as far as the samples reach, but at least half of ``search``); the
    profile's integral is interpolated linearly between samples and extrapolated past the last ones."""
    inside, outside = levels[..., 0], levels[..., 1]
    scaled = (profile - inside[..., None]) / np.where(outside == inside, 1.0, outside - inside)[..., None]
    step = search / STEPS
    integral = np.zeros(scaled.shape, np.float32)
    np.cumsum(0.5 * (scaled[..., 1:] + scaled[..., :-1]), axis=-1, out=integral[..., 1:])
    half = np.maximum(0.5 * search, np.minimum(search - np.abs(centre), 1.0))
    position = (centre[..., None] + np.stack([-half, half], axis=-1) + search[..., None]) / step[..., None]
    below = np.minimum(np.maximum(position, 0.0).astype(np.intp), 2 * STEPS - 1)
    ends = _pick(integral, np.concatenate([below, below + 1], axis=-1))
    at = ends[..., :2] + (position - below) * (ends[..., 2:] - ends[..., :2])
    return centre + half - (at[..., 1] - at[..., 0]) * step


def _pick(values: np.ndarray, index: np.ndarray) -> np.ndarray:
    """``values`` (..., M) at ``index`` (..., K) ints along the last axis: (..., K)."""
    flat = values.reshape(-1, values.shape[-1])
    rows = np.arange(len(flat))[:, None]
    return flat[rows, index.reshape(len(flat), -1)].reshape(index.shape)


def undistort_pixels(pixels: np.ndarray, K: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """(..., 2) undistorted pixels (same ``K``) of (..., 2) distorted ones (cv2.undistortPoints)."""
    flat = pixels.reshape(-1, 1, 2).astype(np.float64)
    return cv2.undistortPoints(flat, K, dist, P=K, criteria=UNDISTORT_CRITERIA).reshape(pixels.shape)


def distort_pixels(pixels: np.ndarray, K: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """(..., 2) distorted pixels of (..., 2) undistorted ones (same ``K``), ``project_points`` of their rays."""
    rays = np.linalg.solve(K, np.c_[pixels.reshape(-1, 2), np.ones(pixels[..., 0].size)].T).T
    return project_points(rays, K, dist).reshape(pixels.shape)


def fit_lines(points: np.ndarray, valid: np.ndarray, iterations: int = REWEIGHTS) -> np.ndarray:
    """Robust total-least-squares lines through batches of 2-D points: a plain fit, then ``iterations``
    refits with Tukey's biweight of the residuals (scale: 1.4826 x their median absolute value).

    ``points``: (..., S, 2) float px; ``valid``: (..., S) bool, the points to use. Returns (..., 3)
    float64 lines ``(a, b, c)`` with ``a * x + b * y + c = 0`` and ``a**2 + b**2 = 1``; NaN where
    fewer than two points are valid. A robust ``cv2.fitLine`` for every batch at once (one call
    instead of one per line).
    """
    x, y = np.ascontiguousarray(points[..., 0]), np.ascontiguousarray(points[..., 1])
    weight = valid.astype(np.float64)
    count = valid.sum(axis=-1)
    middle_index = np.maximum(count - 1, 0)[..., None] // 2
    for refit in range(iterations + 1):
        total = weight.sum(axis=-1)
        total = np.where(total > 0, total, 1.0)
        mean_x, mean_y = (weight * x).sum(axis=-1) / total, (weight * y).sum(axis=-1) / total
        dx, dy = x - mean_x[..., None], y - mean_y[..., None]
        cxx, cyy, cxy = ((weight * dx * dx).sum(axis=-1), (weight * dy * dy).sum(axis=-1),
                         (weight * dx * dy).sum(axis=-1))
        angle = 0.5 * np.arctan2(2 * cxy, cxx - cyy)
        normal_x, normal_y = -np.sin(angle), np.cos(angle)
        if refit == iterations:
            break
        residual = np.abs(dx * normal_x[..., None] + dy * normal_y[..., None])
        ordered = np.sort(np.where(valid, residual, np.inf), axis=-1)
        middle = np.take_along_axis(ordered, middle_index, axis=-1)
        scale = np.maximum(1.4826 * np.where(np.isfinite(middle), middle, 0.0), MIN_SCALE_PX)
        weight = valid * np.clip(1.0 - (residual / (TUKEY_K * scale)) ** 2, 0.0, None) ** 2
    lines = np.stack([normal_x, normal_y, -(normal_x * mean_x + normal_y * mean_y)], axis=-1)
    lines[count < 2] = np.nan
    return lines
