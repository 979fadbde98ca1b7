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
largest, and fails after ``MAX_STEPS`` steps. The seed, the fit and the checks of ``split_two_discs`` run in
compiled code (``merged_kernel.split``, which holds these settings); two or three steps settle most blobs
(``docs/stereo-tracking.md``, Speed).
"""

from __future__ import annotations

import numpy as np

from services.detection.blobs.merged_kernel import MAX_RMS, MIN_GAP_PX, as_weights, split

__all__ = ["MAX_RMS", "MIN_GAP_PX", "TwoDiscs", "split_two_discs"]


class TwoDiscs:
    """A fit of two discs: ``centres`` (2, 2) px (x, y) in the window, ``radii`` (2,) px, ``peak`` (the weight
    of a pixel inside a disc) and ``rms`` (the residual RMS over the window, as a fraction of ``peak``)."""

    __slots__ = ("centres", "peak", "radii", "rms")

    def __init__(self, centres: np.ndarray, radii: np.ndarray, peak: float, rms: float):
        self.centres, self.radii, self.peak, self.rms = centres, radii, peak, rms


def split_two_discs(weights: np.ndarray, centroid: tuple[float, float], axis: tuple[float, float]) -> TwoDiscs | None:
    """The two discs that best explain one blob, or None when the fit fails (no two distinct discs ``MIN_GAP_PX``
    apart or more, or a residual RMS above ``MAX_RMS`` of the peak) or the blob has fewer than ``MIN_PIXELS`` lit
    pixels.

    ``weights``: (h, w) float window of the blob's centroid weights (``measure_kernel.measure``: 0 off the
    blob); ``centroid``: its weighted centroid ``(x, y)`` px in the window; ``axis``: its major axis
    ``(cos, sin)``, a unit vector. The fitted centres come out in the order of their seeds along ``axis``."""
    fitted, params, rms = split(as_weights(weights), centroid[0], centroid[1], axis[0], axis[1])
    return TwoDiscs(params[:4].reshape(2, 2), params[4:6], float(params[6]), rms) if fitted else None
