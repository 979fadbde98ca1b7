"""Similarity transforms (Sim(3)) as 4x4 matrices, and a Sim(3) fitted to matched 3D points by RANSAC.

A similarity ``S = [[s R, t], [0, 1]]`` (4, 4) maps a point ``x`` to ``s R x + t``: scale ``s > 0``,
rotation ``R`` (3, 3), translation ``t`` (3,). Similarities compose and invert as matrices do, so a
rigid pose ``T_camera_world`` is one with ``s = 1``. A monocular map drifts in scale as well as in pose,
so the correction a loop brings is a similarity.

``fit_sim3``: RANSAC over minimal samples of three matches (each solved in closed form by Umeyama's
method with scale, ``services.geometry.absolute_orientation.umeyama_alignment``: for three points it is
Horn's), scored by a caller's residual (a reprojection chi-square in loop closing, a distance by
default); the best hypothesis is refined by Umeyama on its inliers, and the inliers taken again, until
they no longer change.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from services.geometry.absolute_orientation import umeyama_alignment
from services.geometry.se3 import transform_points
from services.geometry.shapes import check_shape

__all__ = ["Sim3Fit", "decompose", "distance_residuals", "fit_sim3", "similarity"]

REFINE_ROUNDS = 5
COLLINEAR = 1e-6
"""A sample whose triangle's area is under this share of its squared longest side is skipped."""


def similarity(scale: float, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(4, 4) the similarity of ``scale``, rotation ``R`` (3, 3) and translation ``t`` (3,)."""
    S = np.eye(4)
    S[:3, :3] = scale * np.asarray(R, np.float64)
    S[:3, 3] = t
    return S


def decompose(S: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """``(scale, R (3, 3), t (3,))`` of the (4, 4) similarity ``S``."""
    scale = float(np.cbrt(np.linalg.det(S[:3, :3])))
    return scale, S[:3, :3] / scale, S[:3, 3].copy()


def distance_residuals(source: np.ndarray, target: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
    """A residual for ``fit_sim3``: each match's squared distance ``|target_i - S source_i|^2``."""
    return lambda S: np.sum((target - transform_points(S, source)) ** 2, axis=1)


@dataclass(frozen=True)
class Sim3Fit:
    """``S_target_source`` (4, 4); ``inliers`` (N,) bool."""

    S_target_source: np.ndarray
    inliers: np.ndarray

    @property
    def count(self) -> int:
        return int(np.count_nonzero(self.inliers))


def _sample_ok(points: np.ndarray) -> bool:
    first, second = points[1] - points[0], points[2] - points[0]
    longest = max(float(first @ first), float(second @ second), float(np.sum((points[2] - points[1]) ** 2)))
    return longest > 0 and float(np.linalg.norm(np.cross(first, second))) > COLLINEAR * longest


def fit_sim3(source: np.ndarray, target: np.ndarray, threshold: float,
             residuals: Callable[[np.ndarray], np.ndarray] | None = None, iterations: int = 200,
             min_inliers: int = 3, seed: int = 0) -> Sim3Fit | None:
    """The similarity ``S`` with ``target_i ~ S source_i`` for (N, 3) matched ``source`` and ``target``
    points (row i with row i), robust to outliers (module docstring).

    ``residuals(S)`` (N,) per match, an inlier's at most ``threshold`` (default: the squared distance,
    ``distance_residuals``). ``iterations`` minimal samples (drawn from ``seed``). None with fewer than
    ``min_inliers`` inliers (at least 3) or fewer than three matches."""
    source = check_shape(source, "N,3", "source", np.float64)
    target = check_shape(target, f"{len(source)},3", "target", np.float64)
    if len(source) < 3:
        return None
    score = residuals if residuals is not None else distance_residuals(source, target)
    rng = np.random.default_rng(seed)
    best: np.ndarray | None = None
    best_count = 0
    for _ in range(iterations):
        sample = rng.choice(len(source), 3, replace=False)
        if not (_sample_ok(source[sample]) and _sample_ok(target[sample])):
            continue
        R, t, s = umeyama_alignment(source[sample], target[sample], with_scale=True)
        inliers = score(similarity(s, R, t)) <= threshold
        count = int(np.count_nonzero(inliers))
        if count > best_count:
            best, best_count = inliers, count
    if best is None or best_count < max(min_inliers, 3):
        return None
    S = np.eye(4)
    for _ in range(REFINE_ROUNDS):
        R, t, s = umeyama_alignment(source[best], target[best], with_scale=True)
        S = similarity(s, R, t)
        again = score(S) <= threshold
        if np.array_equal(again, best) or np.count_nonzero(again) < max(min_inliers, 3):
            break
        best = again
    return Sim3Fit(S, best)
