"""Two spots run into one blob, split: the centres of two discs fitted to the blob's weights.

Pixels as in ``bright``: x right, y down, the centre of the top-left pixel at (0, 0), here of the blob's
window. The model is the image of two bright spheres: two discs of one brightness ``peak`` and radii
``r1``, ``r2`` whose edge ramps linearly over one pixel, the brighter of the two where they overlap::

    model(x) = peak * max(ramp(r1 - |x - p1|), ramp(r2 - |x - p2|)),   ramp(s) = clip(s + 1/2, 0, 1)

``split_two_discs`` seeds it by two means along the blob's major axis (each weighted pixel goes to the
nearer of two centres on the axis, from the halves on either side of the centroid), then fits the seven
numbers ``(p1, p2, r1, r2, peak)`` by least squares (Levenberg-Marquardt) to every pixel of the bounding
box of the blob's weights (so the fit does not depend on how much of the window lies around it).
"""

from __future__ import annotations

import math

import numpy as np
from scipy.optimize import least_squares

__all__ = ["MAX_RMS", "TwoDiscs", "split_two_discs"]

MEANS_ROUNDS = 4
"""Rounds of the two-means seed."""
MAX_RMS = 0.08
"""Largest residual RMS of an accepted fit, as a fraction of its ``peak``."""
MIN_GAP_PX = 0.5
"""Closest the two fitted centres may lie, px: nearer, the blob is one spot."""
MIN_PIXELS = 12
"""Fewest pixels in the box a blob is split in (two discs are seven numbers)."""


class TwoDiscs:
    """A fit of two discs: ``centres`` (2, 2) px (x, y) in the window, ``radii`` (2,) px, ``peak`` (the weight
    of a pixel inside a disc) and ``rms`` (the residual RMS over the window, as a fraction of ``peak``)."""

    __slots__ = ("centres", "peak", "radii", "rms")

    def __init__(self, centres: np.ndarray, radii: np.ndarray, peak: float, rms: float):
        self.centres, self.radii, self.peak, self.rms = centres, radii, peak, rms


def _residuals(params: np.ndarray, xs: np.ndarray, ys: np.ndarray, weights: np.ndarray) -> np.ndarray:
    coverage, _, _, _ = _discs(params, xs, ys)
    return params[6] * coverage - weights


def _jacobian(params: np.ndarray, xs: np.ndarray, ys: np.ndarray, weights: np.ndarray) -> np.ndarray:
    coverage, first, on_ramp, (dx, dy, distance) = _discs(params, xs, ys)
    jac = np.zeros((len(xs), 7))
    rows = np.arange(len(xs))
    ramp = on_ramp * params[6]
    with np.errstate(invalid="ignore", divide="ignore"):
        ux = np.where(distance > 0, dx / distance, 0.0)
        uy = np.where(distance > 0, dy / distance, 0.0)
    disc = np.where(first, 0, 1)
    jac[rows, 2 * disc] = ramp * ux
    jac[rows, 2 * disc + 1] = ramp * uy
    jac[rows, 4 + disc] = ramp
    jac[:, 6] = coverage
    return jac


def _discs(params: np.ndarray, xs: np.ndarray, ys: np.ndarray
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Per pixel: the coverage ``max(ramp_1, ramp_2)``, whether disc 1 gives it, whether it lies on that disc's
    ramp (the slope 1), and the offsets ``(dx, dy)`` from that disc's centre with their length."""
    dx1, dy1 = xs - params[0], ys - params[1]
    dx2, dy2 = xs - params[2], ys - params[3]
    d1, d2 = np.hypot(dx1, dy1), np.hypot(dx2, dy2)
    s1, s2 = params[4] - d1 + 0.5, params[5] - d2 + 0.5
    first = s1 >= s2
    s = np.where(first, s1, s2)
    coverage = np.clip(s, 0.0, 1.0)
    on_ramp = ((s > 0.0) & (s < 1.0)).astype(np.float64)
    return coverage, first, on_ramp, (np.where(first, dx1, dx2), np.where(first, dy1, dy2), np.where(first, d1, d2))


def split_two_discs(weights: np.ndarray, centroid: tuple[float, float], axis: tuple[float, float]) -> TwoDiscs | None:
    """The two discs that best explain one blob, or None when the fit fails (no two distinct discs, or a
    residual RMS above ``MAX_RMS`` of the peak) or the blob has fewer than ``MIN_PIXELS`` lit pixels.

    ``weights``: (h, w) float window of the blob's centroid weights (``bright.Windows.weights``: 0 off the
    blob); ``centroid``: its weighted centroid ``(x, y)`` px in the window; ``axis``: its major axis
    ``(cos, sin)``, a unit vector. The fitted centres come out in the order of their seeds along ``axis``."""
    rows, columns = np.nonzero(weights)
    if len(rows) < MIN_PIXELS:
        return None
    top, left = int(rows.min()), int(columns.min())
    crop = weights[top:int(rows.max()) + 1, left:int(columns.max()) + 1]
    ys, xs = np.mgrid[top:top + crop.shape[0], left:left + crop.shape[1]]
    xs, ys, values = xs.ravel().astype(np.float64), ys.ravel().astype(np.float64), crop.ravel().astype(np.float64)
    lit = values > 0
    direction = np.array(axis, np.float64)
    along = (xs[lit] - centroid[0]) * direction[0] + (ys[lit] - centroid[1]) * direction[1]
    mass = values[lit]
    ends = np.array([-1.0, 1.0])
    for _ in range(MEANS_ROUNDS):
        second = np.abs(along - ends[1]) < np.abs(along - ends[0])
        if second.all() or not second.any():
            return None
        ends = np.array([np.average(along[~second], weights=mass[~second]),
                         np.average(along[second], weights=mass[second])])
    peak = float(mass.max())
    shares = np.array([mass[~second].sum(), mass[second].sum()]) / peak
    start = np.array([centroid[0] + ends[0] * direction[0], centroid[1] + ends[0] * direction[1],
                      centroid[0] + ends[1] * direction[0], centroid[1] + ends[1] * direction[1],
                      math.sqrt(shares[0] / math.pi), math.sqrt(shares[1] / math.pi), peak])
    fit = least_squares(_residuals, start, _jacobian, method="lm", args=(xs, ys, values))
    params = fit.x
    centres = params[:4].reshape(2, 2)
    radii = params[4:6]
    rms = float(np.sqrt(np.mean(fit.fun**2))) / params[6] if params[6] > 0 else math.inf
    if (not fit.success or rms > MAX_RMS or np.any(radii <= 0.0)
            or np.linalg.norm(centres[0] - centres[1]) < MIN_GAP_PX):
        return None
    return TwoDiscs(centres, radii, float(params[6]), rms)
