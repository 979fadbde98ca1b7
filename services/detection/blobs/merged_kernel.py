"""Compiled code for blobs that may be two spots run together (``numba``), run without Python's global lock:
the waist test that tells a merged blob from an occluded one (``has_waist``) and the fit of two discs that
splits it (``split``). ``bright.shape_flags`` and ``split.split_two_discs`` state the methods; here they are
loops over a blob's pixels instead of a few dozen NumPy calls on arrays of a few hundred.

Pixels as in ``bright``: x right, y down, the centre of the top-left pixel at (0, 0), here of the blob's
window. Cached on disk beside this module (``cache=True``).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

__all__ = ["MAX_RMS", "MIN_GAP_PX", "as_weights", "cholesky_solve", "has_waist", "split", "warm"]

PARAMETERS = 7
"""The two-disc model's numbers: ``(x1, y1, x2, y2, r1, r2, peak)``."""
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
"""Levenberg-Marquardt damping: its start (a fraction of the normal matrix's diagonal at the start), the factor it
grows by after a step that raises the cost and shrinks by after one that lowers it, and the largest it may grow
to before the fit stops where it is."""
PIVOT_EPSILON = np.finfo(np.float64).eps
"""A Cholesky pivot below this means the matrix is not positive definite (``cv2.solve``'s rule)."""


@njit(cache=True, nogil=True)
def has_waist(weights: np.ndarray, cx: float, cy: float, ax: float, ay: float, depth: float) -> bool:
    """Whether the weight of (h, w) float32 or float64 ``weights`` (0 off the blob), summed across the unit axis
    ``(ax, ay)`` in 1 px slices (each pixel shared linearly between the two nearest slices, its position along
    the axis measured from the centroid ``(cx, cy)`` px), dips somewhere inside below ``1 - depth`` of the
    heaviest slice on each side."""
    height, width = weights.shape
    count = 0
    lowest = math.inf
    along = np.empty(height * width)
    values = np.empty(height * width)
    for y in range(height):
        for x in range(width):
            if weights[y, x] != 0.0:
                position = (x - cx) * ax + (y - cy) * ay
                along[count] = position
                values[count] = weights[y, x]
                lowest = min(lowest, position)
                count += 1
    highest = 0
    for i in range(count):
        along[i] -= lowest
        highest = max(highest, int(along[i]))
    size = highest + 2
    if size < 3:
        return False
    lower, upper = np.zeros(size), np.zeros(size)
    for i in range(count):
        index = int(along[i])
        share = along[i] - index
        lower[index] += values[i] * (1.0 - share)
        upper[index + 1] += values[i] * share
    profile = lower + upper
    right = np.empty(size)
    right[size - 1] = profile[size - 1]
    for i in range(size - 2, -1, -1):
        right[i] = max(right[i + 1], profile[i])
    left = profile[0]
    for i in range(1, size - 1):
        if profile[i] < (1.0 - depth) * min(left, right[i + 1]):
            return True
        left = max(left, profile[i])
    return False


@njit(cache=True, nogil=True)
def cholesky_solve(matrix: np.ndarray, vector: np.ndarray) -> tuple[bool, np.ndarray]:
    """``(solved, x)`` with ``matrix @ x = vector`` for an (n, n) symmetric ``matrix`` by its Cholesky factor
    (its lower triangle read), and ``solved`` False, as ``cv2.solve(..., cv2.DECOMP_CHOLESKY)`` says, when a
    pivot falls below ``PIVOT_EPSILON`` (not positive definite)."""
    n = len(vector)
    lower = np.zeros((n, n))
    for i in range(n):
        for j in range(i + 1):
            total = matrix[i, j]
            for k in range(j):
                total -= lower[i, k] * lower[j, k]
            if i == j:
                if total < PIVOT_EPSILON:
                    return False, np.zeros(n)
                lower[i, i] = math.sqrt(total)
            else:
                lower[i, j] = total / lower[j, j]
    solution = np.empty(n)
    for i in range(n):
        total = vector[i]
        for k in range(i):
            total -= lower[i, k] * solution[k]
        solution[i] = total / lower[i, i]
    for i in range(n - 1, -1, -1):
        total = solution[i]
        for k in range(i + 1, n):
            total -= lower[k, i] * solution[k]
        solution[i] = total / lower[i, i]
    return True, solution


@njit(cache=True, nogil=True)
def _model(params: np.ndarray, xs: np.ndarray, ys: np.ndarray, values: np.ndarray, rows: np.ndarray) -> None:
    """Into ``rows`` (8, N): the Jacobian of the residuals ``model - values`` at ``params`` (7,) (rows 0-6, one
    per parameter) and the residuals (row 7), for pixel centres ``xs``, ``ys`` (N,) px and weights ``values``
    (N,). A pixel's ramp is that of the disc giving it; its slope is 1 from one end to the other, 0 beyond."""
    peak = params[6]
    for i in range(len(values)):
        x1, y1 = xs[i] - params[0], ys[i] - params[1]
        x2, y2 = xs[i] - params[2], ys[i] - params[3]
        d1, d2 = math.hypot(x1, y1), math.hypot(x2, y2)
        reach1, reach2 = params[4] + 0.5 - d1, params[5] + 0.5 - d2
        edge = max(reach1, reach2)
        coverage = min(max(edge, 0.0), 1.0)
        slope = peak if coverage == edge else 0.0
        slope1 = slope if reach1 >= reach2 else 0.0
        slope2 = slope - slope1
        scale1, scale2 = slope1 / max(d1, 1e-12), slope2 / max(d2, 1e-12)
        rows[0, i], rows[1, i], rows[2, i], rows[3, i] = x1 * scale1, y1 * scale1, x2 * scale2, y2 * scale2
        rows[4, i], rows[5, i], rows[6, i] = slope1, slope2, coverage
        rows[7, i] = coverage * peak - values[i]


@njit(cache=True, nogil=True)
def _gram(rows: np.ndarray, products: np.ndarray) -> None:
    """Into ``products`` (8, 8): ``rows @ rows.T`` of (8, N) ``rows``."""
    for a in range(8):
        for b in range(a + 1):
            total = 0.0
            for i in range(rows.shape[1]):
                total += rows[a, i] * rows[b, i]
            products[a, b] = total
            products[b, a] = total


@njit(cache=True, nogil=True)
def _fit(start: np.ndarray, xs: np.ndarray, ys: np.ndarray, values: np.ndarray) -> tuple[bool, np.ndarray, np.ndarray]:
    """``(settled, params, residuals)``: the parameters (7,) nearest ``start`` minimising the squared residuals of
    ``_model`` by Levenberg-Marquardt, and the residuals (N,) there (``split`` states the steps); ``settled`` False
    when ``MAX_STEPS`` steps do not settle them."""
    damping, factor, most = DAMPING
    count = len(values)
    params = start.copy()
    rows, trial_rows = np.empty((8, count)), np.empty((8, count))
    products, trial_products = np.empty((8, 8)), np.empty((8, 8))
    _model(params, xs, ys, values, rows)
    _gram(rows, products)
    largest = 0.0
    for i in range(PARAMETERS):
        largest = max(largest, products[i, i])
    scaling = np.empty(PARAMETERS)
    for i in range(PARAMETERS):
        scaling[i] = max(products[i, i], 1e-12 * largest)
    normal = np.empty((PARAMETERS, PARAMETERS))
    gradient = np.empty(PARAMETERS)
    for _ in range(MAX_STEPS):
        for i in range(PARAMETERS):
            for j in range(PARAMETERS):
                normal[i, j] = products[i, j]
            normal[i, i] += damping * scaling[i]
            gradient[i] = -products[i, 7]
        solved, step = cholesky_solve(normal, gradient)
        if solved:
            move = 0.0
            for i in range(6):
                move = max(move, abs(step[i]))
            if move < STEP_TOLERANCE:
                return True, params, rows[7].copy()
            if move > MAX_MOVE_PX:
                step *= MAX_MOVE_PX / move
            trial = params + step
            _model(trial, xs, ys, values, trial_rows)
            _gram(trial_rows, trial_products)
            if trial_products[7, 7] <= products[7, 7]:
                params = trial
                rows, trial_rows = trial_rows, rows
                products, trial_products = trial_products, products
                damping = max(damping / factor, 1e-12)
                continue
        damping *= factor
        if damping > most:
            return True, params, rows[7].copy()
    return False, params, rows[7].copy()


@njit(cache=True, nogil=True)
def _seed(weights: np.ndarray, cx: float, cy: float, ax: float, ay: float) -> tuple[bool, np.ndarray]:
    """``(seeded, start)``: the fit's start (7,) from the lit pixels of (h, w) ``weights``, two means along the
    unit axis ``(ax, ay)`` from the centroid ``(cx, cy)`` (``split`` states the rule);
    ``seeded`` False when a round leaves a mean without pixels."""
    height, width = weights.shape
    along = np.empty(height * width)
    mass = np.empty(height * width)
    count = 0
    peak = 0.0
    for y in range(height):
        for x in range(width):
            if weights[y, x] != 0.0:
                along[count] = (x - cx) * ax + (y - cy) * ay
                mass[count] = weights[y, x]
                peak = max(peak, weights[y, x])
                count += 1
    order = np.argsort(along[:count])
    sorted_along = along[:count][order]
    heavy = np.cumsum(mass[:count][order])
    moment = np.cumsum(mass[:count][order] * sorted_along)
    low, high = -1.0, 1.0
    near, total = 0.0, heavy[count - 1]
    for _ in range(MEANS_ROUNDS):
        cut = np.searchsorted(sorted_along, 0.5 * (low + high), side="right")
        if cut == 0 or cut == count:
            return False, np.zeros(PARAMETERS)
        near = heavy[cut - 1]
        low, high = moment[cut - 1] / near, (moment[count - 1] - moment[cut - 1]) / (total - near)
    start = np.array([cx + low * ax, cy + low * ay, cx + high * ax, cy + high * ay,
                      math.sqrt(near / (math.pi * peak)), math.sqrt((total - near) / (math.pi * peak)), peak])
    return True, start


@njit(cache=True, nogil=True)
def split(weights: np.ndarray, cx: float, cy: float, ax: float, ay: float) -> tuple[bool, np.ndarray, float]:
    """``(fitted, params, rms)``: two discs fitted to (h, w) ``weights`` (0 off the blob; float32 or float64) from
    the blob's centroid ``(cx, cy)`` px and unit major axis ``(ax, ay)``, ``params`` ``(x1, y1, x2, y2, r1, r2,
    peak)`` px in the window (the centres in the order of their seeds along the axis) and ``rms`` the residual
    RMS over the lit pixels' bounding box as a fraction of ``peak``.

    ``fitted`` is False with fewer than ``MIN_PIXELS`` lit pixels, no seed, no settled fit, a residual RMS above
    ``MAX_RMS``, a radius not above 0 or the centres nearer than ``MIN_GAP_PX``. The method:
    ``split.split_two_discs``'s docstring."""
    height, width = weights.shape
    top, bottom, left, right, lit = height, -1, width, -1, 0
    for y in range(height):
        for x in range(width):
            if weights[y, x] != 0.0:
                top, bottom = min(top, y), max(bottom, y)
                left, right = min(left, x), max(right, x)
                lit += 1
    if lit < MIN_PIXELS:
        return False, np.zeros(PARAMETERS), math.inf
    seeded, start = _seed(weights, cx, cy, ax, ay)
    if not seeded:
        return False, start, math.inf
    box = (bottom + 1 - top) * (right + 1 - left)
    xs, ys, values = np.empty(box), np.empty(box), np.empty(box)
    i = 0
    for y in range(top, bottom + 1):
        for x in range(left, right + 1):
            xs[i], ys[i], values[i] = x, y, weights[y, x]
            i += 1
    settled, params, residuals = _fit(start, xs, ys, values)
    peak = params[6]
    rms = math.sqrt(np.dot(residuals, residuals) / box) / peak if peak > 0.0 else math.inf
    fitted = (settled and rms <= MAX_RMS and min(params[4], params[5]) > 0.0
              and math.hypot(params[2] - params[0], params[3] - params[1]) >= MIN_GAP_PX)
    return fitted, params, rms


def as_weights(weights: np.ndarray) -> np.ndarray:
    """``weights`` as a C-ordered float32 (kept so) or float64 array: the depths these kernels are built for."""
    return np.ascontiguousarray(weights, np.float32 if weights.dtype == np.float32 else np.float64)


def warm() -> None:
    """``has_waist`` and ``split`` (with ``cholesky_solve``) run once on a tiny blob of two discs in each float
    depth: compiled, or loaded from the cache."""
    yy, xx = np.mgrid[0:9, 0:14]
    weights = 100.0 * ((np.hypot(xx - 4.0, yy - 4.0) <= 3.0) | (np.hypot(xx - 9.0, yy - 4.0) <= 3.0))
    for depth in (np.float32, np.float64):
        has_waist(weights.astype(depth), 6.5, 4.0, 1.0, 0.0, 0.05)
        split(weights.astype(depth), 6.5, 4.0, 1.0, 0.0)
