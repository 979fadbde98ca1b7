"""The blob centroids' noise, estimated from the reprojection residuals of the points triangulated from them.

A point seen in ``v`` views and refined by least squares leaves residuals (observed - projected, px) whose
sum of squares is ``sigma_px^2 chi2(2v - 3)`` when every centroid coordinate has independent noise of
``sigma_px`` (2v coordinates, 3 taken by the point): ``sum r^2 / (2v - 3)`` estimates ``sigma_px^2``
without bias. A two-view point gives one degree of freedom (its epipolar distance), a three-view point three.

``CentroidNoise`` pools the points of the last ``window`` sets robustly: a median-based scale first
(each point's sum of squares over the median of its ``chi2(2v - 3)``), then the points beyond that scale's
``keep`` quantile are dropped as wrong correspondences and the rest pooled, their expectation corrected for the
truncation (``E[chi2_d | chi2_d <= q] = d F_{d+2}(q) / F_d(q)``). The estimate is bounded below by ``floor_px``
and is ``prior_px`` until a residual has been seen.

What the residuals see is the part of the centroid error that differs between views. An error common to
every view of a point (the centroid of a sphere's image is not quite the image of its centre: a shift of
about ``(r / z)^2`` times the distance from the principal point, 0.001 px for 8 mm spheres 2 m away)
moves the point without a residual and is not counted; it is far below the detector's own error.
"""

from __future__ import annotations

from collections import deque
from functools import cache

import numpy as np
from scipy.special import chdtr, chdtri

__all__ = ["CentroidNoise", "degrees_of_freedom", "robust_variance"]

_TABLE_ROWS = 16
"""Rows of the constants' table made at first (degrees of freedom up to 15: a point seen in nine views)."""


def degrees_of_freedom(views: np.ndarray) -> np.ndarray:
    """(N,) int64 ``2 v - 3`` of (N,) view counts ``v`` (0 for fewer than two views)."""
    return np.maximum(2 * np.asarray(views, np.int64) - 3, 0)


def robust_variance(squares: np.ndarray, dof: np.ndarray, keep: float = 0.999) -> float | None:
    """``sigma_px^2`` (px^2) from (N,) sums of squared residuals (px^2) with (N,) ``dof`` each (> 0 counted);
    None without a point of positive ``dof``. See the module's docstring for the estimator."""
    table = _usable_table(np.asarray(squares, np.float64), np.asarray(dof, np.int64), keep)
    return _pooled_variance(table) if table.shape[1] else None


def _usable_table(squares: np.ndarray, dof: np.ndarray, keep: float) -> np.ndarray:
    """(4, K) float64: the points with positive ``dof`` and a finite sum of squares, in order, as columns
    ``(sum of squares, chi2 median, chi2 keep quantile, expected share)`` (``_chi2_constants`` of their dof)."""
    usable = (dof > 0) & np.isfinite(squares)
    kept = dof[usable]
    constants = _chi2_table(int(kept.max(initial=0)), keep)[kept]
    return np.vstack([squares[usable], constants.T])


def _pooled_variance(table: np.ndarray) -> float:
    """The robust pooled ``sigma_px^2`` of the points of a ``_usable_table`` (at least one)."""
    squares, median, limit, expected = table
    scale = _median(squares / median)
    if scale <= 0.0:
        return 0.0
    kept = squares <= scale * limit
    return float(np.sum(squares[kept]) / np.sum(expected[kept]))


def _median(values: np.ndarray) -> float:
    """The median of (N,) finite ``values``, N >= 1 (``np.median``'s, without its checks and dispatch)."""
    middle = values.size // 2
    if values.size % 2:
        return float(np.partition(values, middle)[middle])
    lower, upper = np.partition(values, (middle - 1, middle))[middle - 1:middle + 1]
    return 0.5 * float(lower + upper)


def _chi2_table(largest: int, keep: float) -> np.ndarray:
    """(D, 3) float64 with D > ``largest``: row ``d`` the ``_chi2_constants`` of ``d`` (row 0 unused, zeros)."""
    rows = _TABLE_ROWS
    while rows <= largest:
        rows *= 2
    return _chi2_rows(rows, keep)


@cache
def _chi2_rows(rows: int, keep: float) -> np.ndarray:
    """(rows, 3) read-only float64: ``_chi2_constants`` of 1 to ``rows - 1`` degrees of freedom, row 0 zeros."""
    table = np.zeros((rows, 3))
    for dof in range(1, rows):
        table[dof] = _chi2_constants(dof, keep)
    table.flags.writeable = False
    return table


def _chi2_constants(dof: int, keep: float) -> tuple[float, float, float]:
    """For ``chi2(dof)``: its median, its ``keep`` quantile, and its mean below that quantile over ``keep``
    (the expected share of a kept point's sum of squares). ``scipy.special``'s chi-square functions, the ones
    ``scipy.stats.chi2`` calls, whose module takes about a second to import on a 2-core VM."""
    limit = float(chdtri(dof, 1.0 - keep))
    return float(chdtri(dof, 0.5)), limit, float(dof * chdtr(dof + 2, limit) / keep)


class CentroidNoise:
    """A running estimate of the centroid noise ``sigma_px`` (px per coordinate) over the last ``window`` sets.

    ``update`` takes one set's points: (N,) ``rms_px`` (root mean square over its views of the reprojection
    error's length, as ``TriangulatedPoint.rms_px``) and (N,) ``views``. The window's usable points are kept
    as one ``_usable_table``, oldest set first, and ``sizes`` counts each set's columns in it.
    """

    def __init__(self, window: int = 100, floor_px: float = 0.005, prior_px: float = 0.1, keep: float = 0.999):
        if window < 1 or not (0.0 < floor_px <= prior_px) or not (0.5 < keep < 1.0):
            raise ValueError(f"need window >= 1, 0 < floor_px <= prior_px and 0.5 < keep < 1, got {window}, "
                             f"{floor_px}, {prior_px} and {keep}")
        self.floor_px, self.prior_px, self.keep = floor_px, prior_px, keep
        self.sizes: deque[int] = deque(maxlen=window)
        self.table = np.zeros((4, 0))
        self.sigma_px = prior_px

    def update(self, rms_px: np.ndarray, views: np.ndarray) -> float:
        """Take in one set's points and return the estimate (px)."""
        views = np.asarray(views, np.int64)
        dof = degrees_of_freedom(views)
        if np.any(dof > 0):
            squares = np.square(np.asarray(rms_px, np.float64)) * views
            added = _usable_table(squares, dof, self.keep)
            forgotten = self.sizes[0] if len(self.sizes) == self.sizes.maxlen else 0
            self.sizes.append(added.shape[1])
            self.table = np.concatenate([self.table[:, forgotten:], added], axis=1)
            if self.table.shape[1]:
                self.sigma_px = max(float(np.sqrt(_pooled_variance(self.table))), self.floor_px)
        return self.sigma_px
