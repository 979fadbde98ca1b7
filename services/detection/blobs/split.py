"""Two spots run into one blob, split: the centres of two discs fitted to the blob's weights.

Pixels as in ``bright``: x right, y down, the centre of the top-left pixel at (0, 0), here of the blob's
window. The model is the image of two bright spheres: two discs of one brightness ``peak`` and radii
``r1``, ``r2`` whose edge ramps linearly over one pixel, the brighter of the two where they overlap::

    model(x) = peak * max(ramp(r1 - |x - p1|), ramp(r2 - |x - p2|)),   ramp(s) = clip(s + 1/2, 0, 1)

``split_two_discs`` seeds it by two means along the blob's major axis (each weighted pixel goes to the
nearer of two centres on the axis, from the halves on either side of the centroid), then fits the seven
numbers ``(p1, p2, r1, r2, peak)`` by least squares to every pixel of the bounding box of the blob's
weights (so the fit does not depend on how much of the window lies around it) by Levenberg-Marquardt
(``_fit``): each step one pass of numpy calls over the box's pixels for the residuals and their Jacobian,
then the 7x7 normal equations solved by Cholesky, each step moving a centre or radius ``MAX_MOVE_PX`` at
most, until the next would move none by ``STEP_TOLERANCE``. Two or three steps settle most blobs, 0.1 to
0.2 ms a blob (``docs/stereo-tracking.md``, Speed).
"""

from __future__ import annotations

import bisect
import math

import cv2
import numpy as np

__all__ = ["MAX_RMS", "TwoDiscs", "split_two_discs"]

MEANS_ROUNDS = 4
"""Rounds of the two-means seed."""
MAX_RMS = 0.08
"""Largest residual RMS of an accepted fit, as a fraction of its ``peak``."""
MIN_GAP_PX = 0.5
"""Closest the two fitted centres may lie, px: nearer, the blob is one spot."""
MIN_PIXELS = 12
"""Fewest pixels in the box a blob is split in (two discs are seven numbers)."""
MAX_STEPS = 40
"""Most Levenberg-Marquardt steps tried (accepted or not) before the fit is given up."""
STEP_TOLERANCE = 1e-4
"""A step moving no centre or radius by more than this, px, ends the fit."""
MAX_MOVE_PX = 0.5
"""Farthest one step moves a centre or a radius, px: a longer step is shortened to this, its direction kept."""
DAMPING = (1e-3, 10.0, 1e8)
"""Levenberg-Marquardt damping: its start (a fraction of the normal matrix's diagonal at the start), the factor it grows
by after a step that raises the cost and shrinks by after one that lowers it, and the largest it may grow
to before the fit stops where it is."""


class TwoDiscs:
    """A fit of two discs: ``centres`` (2, 2) px (x, y) in the window, ``radii`` (2,) px, ``peak`` (the weight
    of a pixel inside a disc) and ``rms`` (the residual RMS over the window, as a fraction of ``peak``)."""

    __slots__ = ("centres", "peak", "radii", "rms")

    def __init__(self, centres: np.ndarray, radii: np.ndarray, peak: float, rms: float):
        self.centres, self.radii, self.peak, self.rms = centres, radii, peak, rms


def _model(params: np.ndarray, points: np.ndarray, values: np.ndarray) -> np.ndarray:
    """(8, N): the Jacobian of the residuals ``model - values`` at ``params`` (7,) ``(p1, p2, r1, r2, peak)``
    (rows 0-6, a row per parameter) and the residuals (row 7), for pixel centres ``points`` (2, N) px and
    weights ``values`` (N,). A pixel's ramp is that of the disc giving it; its slope is 1 from one end to the
    other, 0 beyond."""
    offsets = points - params[:4].reshape(2, 2, 1)
    distances = np.hypot(offsets[:, 0], offsets[:, 1])
    reach = params[4:6, None] + 0.5 - distances
    first = reach[0] >= reach[1]
    edge = np.maximum(reach[0], reach[1])
    rows = np.empty((8, len(values)))
    coverage = rows[6]
    np.minimum(np.maximum(edge, 0.0), 1.0, out=coverage)
    np.multiply(coverage == edge, params[6], out=rows[5])
    np.multiply(rows[5], first, out=rows[4])
    rows[5] -= rows[4]
    np.multiply(offsets, (rows[4:6] / np.maximum(distances, 1e-12))[:, None], out=rows[:4].reshape(2, 2, -1))
    np.multiply(coverage, params[6], out=rows[7])
    rows[7] -= values
    return rows


def _fit(start: np.ndarray, points: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """The parameters (7,) nearest ``start`` (7,) minimising the squared residuals of ``_model``, and the
    residuals (N,) there; None when ``MAX_STEPS`` steps do not settle them.

    Each step solves ``(J J^T + damping D) step = -J r`` (Cholesky), ``D`` the diagonal of ``J J^T`` at
    ``start``, and is shortened to move nothing more than ``MAX_MOVE_PX``; the fit ends before a step moving
    nothing more than ``STEP_TOLERANCE``, or where no step lowers the cost before the damping passes its
    largest."""
    params = start
    rows = _model(params, points, values)
    products = rows @ rows.T
    diagonal = products.diagonal()[:7]
    scaling = np.diag(np.maximum(diagonal, 1e-12 * diagonal.max()))
    damping, factor, most = DAMPING
    for _ in range(MAX_STEPS):
        solved, step = cv2.solve(products[:7, :7] + damping * scaling, -products[:7, 7:], flags=cv2.DECOMP_CHOLESKY)
        if solved:
            step = step[:, 0]
            move = max(map(abs, step[:6].tolist()))
            if move < STEP_TOLERANCE:
                return params, rows[7]
            if move > MAX_MOVE_PX:
                step *= MAX_MOVE_PX / move
            trial = params + step
            trial_rows = _model(trial, points, values)
            trial_products = trial_rows @ trial_rows.T
            if trial_products[7, 7] <= products[7, 7]:
                params, rows, products = trial, trial_rows, trial_products
                damping = max(damping / factor, 1e-12)
                continue
        damping *= factor
        if damping > most:
            return params, rows[7]
    return None


def _seed(mass: np.ndarray, xs: np.ndarray, ys: np.ndarray, centroid: tuple[float, float],
          axis: tuple[float, float]) -> np.ndarray | None:
    """The fit's start ``(p1, p2, r1, r2, peak)`` (7,) from the blob's lit pixels (weights ``mass``, columns
    ``xs`` and rows ``ys``, (M,) each): two means along ``axis`` from ``centroid`` (``MEANS_ROUNDS`` rounds,
    each pixel to the nearer mean, the nearer-to-the-first at an equal distance), each disc of the area its
    pixels' weights make at the heaviest one's; None when a round leaves a mean without pixels."""
    along = (xs - centroid[0]) * axis[0] + (ys - centroid[1]) * axis[1]
    order = np.argsort(along)
    along = along[order]
    heavy_list = np.cumsum(mass[order]).tolist()
    moment = np.cumsum(mass[order] * along).tolist()
    along_list = along.tolist()
    ends = (-1.0, 1.0)
    for _ in range(MEANS_ROUNDS):
        cut = bisect.bisect_right(along_list, 0.5 * (ends[0] + ends[1]))
        if cut in (0, len(along_list)):
            return None
        near, total = heavy_list[cut - 1], heavy_list[-1]
        ends = (moment[cut - 1] / near, (moment[-1] - moment[cut - 1]) / (total - near))
    peak = float(mass.max())
    return np.array([centroid[0] + ends[0] * axis[0], centroid[1] + ends[0] * axis[1],
                     centroid[0] + ends[1] * axis[0], centroid[1] + ends[1] * axis[1],
                     math.sqrt(near / (math.pi * peak)), math.sqrt((total - near) / (math.pi * peak)), peak])


def split_two_discs(weights: np.ndarray, centroid: tuple[float, float], axis: tuple[float, float]) -> TwoDiscs | None:
    """The two discs that best explain one blob, or None when the fit fails (no two distinct discs, or a
    residual RMS above ``MAX_RMS`` of the peak) or the blob has fewer than ``MIN_PIXELS`` lit pixels.

    ``weights``: (h, w) float window of the blob's centroid weights (``measure_kernel.measure``: 0 off the
    blob); ``centroid``: its weighted centroid ``(x, y)`` px in the window; ``axis``: its major axis
    ``(cos, sin)``, a unit vector. The fitted centres come out in the order of their seeds along ``axis``."""
    rows, columns = np.nonzero(weights)
    if len(rows) < MIN_PIXELS:
        return None
    start = _seed(weights[rows, columns].astype(np.float64), columns, rows, centroid, axis)
    if start is None:
        return None
    top, bottom = int(rows[0]), int(rows[-1]) + 1  # np.nonzero gives the rows in ascending order
    left, right = int(columns.min()), int(columns.max()) + 1
    points = np.empty((2, bottom - top, right - left))
    points[0] = np.arange(left, right)
    points[1] = np.arange(top, bottom)[:, None]
    values = weights[top:bottom, left:right].astype(np.float64).ravel()
    fit = _fit(start, points.reshape(2, -1), values)
    if fit is None:
        return None
    params, residuals = fit
    x1, y1, x2, y2, r1, r2, peak = params.tolist()
    rms = math.sqrt(float(residuals @ residuals) / len(residuals)) / peak if peak > 0.0 else math.inf
    if rms > MAX_RMS or min(r1, r2) <= 0.0 or math.hypot(x2 - x1, y2 - y1) < MIN_GAP_PX:
        return None
    return TwoDiscs(params[:4].reshape(2, 2), params[4:6], peak, rms)
