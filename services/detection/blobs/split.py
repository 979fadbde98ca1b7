"""Two spots run into one blob, split: the centres of two discs fitted to the blob's weights.

Pixels as in ``bright``: x right, y down, the centre of the top-left pixel at (0, 0), here of the blob's
window. The model is the image of two bright spheres: two discs of one brightness ``peak`` and radii
``r1``, ``r2`` whose edge ramps linearly over one pixel, the brighter of the two where they overlap::

    model(x) = peak * max(ramp(r1 - |x - p1|), ramp(r2 - |x - p2|)),   ramp(s) = clip(s + 1/2, 0, 1)

``split_two_discs`` seeds it by two means along the blob's major axis (each weighted pixel goes to the
nearer of two centres on the axis, from the halves on either side of the centroid), then fits the seven
numbers ``(p1, p2, r1, r2, peak)`` by least squares to every pixel of the bounding box of the blob's
weights (so the fit does not depend on how much of the window lies around it) by Levenberg-Marquardt:
each step one pass over the box's pixels for the residuals and their Jacobian, then the 7x7 normal
equations ``(J J^T + damping D) step = -J r`` solved by Cholesky (``D`` the diagonal of ``J J^T`` at the
start), each step shortened to move a centre or radius ``MAX_MOVE_PX`` at most; the fit ends before a step
that would move none by ``STEP_TOLERANCE``, or where no step lowers the cost before the damping passes its
largest, and fails after ``MAX_STEPS`` steps. The seed and the fit run in compiled code
(``merged_kernel.split``); two or three steps settle most blobs (``docs/stereo-tracking.md``, Speed).
"""

from __future__ import annotations

import math

import numpy as np

from services.detection.blobs.merged_kernel import split

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


def split_two_discs(weights: np.ndarray, centroid: tuple[float, float], axis: tuple[float, float]) -> TwoDiscs | None:
    """The two discs that best explain one blob, or None when the fit fails (no two distinct discs, or a
    residual RMS above ``MAX_RMS`` of the peak) or the blob has fewer than ``MIN_PIXELS`` lit pixels.

    ``weights``: (h, w) float window of the blob's centroid weights (``measure_kernel.measure``: 0 off the
    blob); ``centroid``: its weighted centroid ``(x, y)`` px in the window; ``axis``: its major axis
    ``(cos, sin)``, a unit vector. The fitted centres come out in the order of their seeds along ``axis``."""
    fitted, params, rms = split(np.ascontiguousarray(weights, np.float64), centroid[0], centroid[1], axis[0], axis[1],
                                MIN_PIXELS, MEANS_ROUNDS, MAX_STEPS, STEP_TOLERANCE, MAX_MOVE_PX, *DAMPING)
    if not fitted:
        return None
    x1, y1, x2, y2, r1, r2, peak = params.tolist()
    if rms > MAX_RMS or min(r1, r2) <= 0.0 or math.hypot(x2 - x1, y2 - y1) < MIN_GAP_PX:
        return None
    return TwoDiscs(params[:4].reshape(2, 2), params[4:6], peak, rms)
