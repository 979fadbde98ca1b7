"""Scoring estimated poses against ground truth, in the field's terms.

Poses are (4, 4) ``T_a_b`` of the same two frames; rotation errors are radians, translation
errors metres (callers convert to degrees, millimetres or % of distance for reports).

Trajectories are (N, 4, 4) float64 ``T_world_body`` poses (or, where only positions matter,
(N, 3) float64 positions in the world frame), row i of the estimate matched to row i of the
ground truth (``associate`` finds those rows from the stamps). The two worlds may differ:

* ``umeyama``: the similarity ``p_gt = s R p_est + t`` that best maps estimated positions onto
  true ones in the least-squares sense (Umeyama, 1991); ``s = 1`` for a rigid (SE(3)) alignment.
* ``absolute_trajectory_error`` (ATE): the distances between true and aligned estimated
  positions after such an alignment (SE(3) for stereo or metric trackers, Sim(3) for monocular).
* ``relative_pose_error`` (RPE): the error of the motion between pairs of poses a fixed number
  of frames, or a fixed travelled distance (along the ground truth), apart; every such pair is
  used (overlapping pairs, as TUM's benchmark tools do). It measures drift and needs no
  alignment, but for a monocular estimate its translations are scaled by ``scale`` first.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from services.geometry.absolute_orientation import umeyama_alignment
from services.geometry.rotation import rotation_angle, rotation_angles
from services.geometry.shapes import check_shape

__all__ = [
    "ALIGNMENTS",
    "DELTA_UNITS",
    "AbsoluteError",
    "Alignment",
    "DeltaUnit",
    "ErrorStats",
    "RelativeError",
    "Similarity",
    "TrajectoryScore",
    "absolute_trajectory_error",
    "apply_similarity",
    "associate",
    "error_stats",
    "pose_error",
    "relative_pose_error",
    "rpe_pairs",
    "score_trajectory",
    "umeyama",
]

Alignment = Literal["se3", "sim3", "none"]
DeltaUnit = Literal["frames", "m"]
ALIGNMENTS: tuple[str, ...] = ("se3", "sim3", "none")
DELTA_UNITS: tuple[str, ...] = ("frames", "m")
PATH_TOLERANCE_M = 1e-9
"""Slack on the travelled distance when pairing rows ``delta`` metres apart (rounding of summed steps)."""


def pose_error(T_est: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    """``(rotation error rad, translation error m)`` of an estimate ``T_a_b`` against the true ``T_a_b``.

    The rotation error is the angle of ``R_est^T R_true``; the translation error is the distance
    between the two origins of frame b expressed in frame a.
    """
    T_est, T_true = check_shape(T_est, "4,4", "T_est", np.float64), check_shape(T_true, "4,4", "T_true", np.float64)
    return rotation_angle(T_est[:3, :3], T_true[:3, :3]), float(np.linalg.norm(T_est[:3, 3] - T_true[:3, 3]))


@dataclass(frozen=True)
class Similarity:
    """``p_a = s R p_b + t``: (3, 3) rotation ``R``, (3,) translation ``t`` (m), scale ``s`` (1 for rigid)."""

    R: np.ndarray
    t: np.ndarray
    s: float = 1.0

    @classmethod
    def identity(cls) -> Similarity:
        """``s = 1``, ``R = I``, ``t = 0``."""
        return cls(np.eye(3), np.zeros(3), 1.0)

    @property
    def matrix(self) -> np.ndarray:
        """(4, 4) ``[[s R, t], [0, 1]]``."""
        M = np.eye(4)
        M[:3, :3] = self.s * self.R
        M[:3, 3] = self.t
        return M

    def apply(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) points (or one (3,) point) mapped: ``s R p + t``."""
        return self.s * check_shape(points, "*,3", "points", np.float64) @ self.R.T + self.t


def _positions(name: str, array: np.ndarray) -> np.ndarray:
    """(N, 3) positions of (N, 3) positions or (N, 4, 4) poses; ValueError naming ``name`` otherwise."""
    array = np.asarray(array, dtype=np.float64)
    if array.ndim == 3 and array.shape[1:] == (4, 4):
        return array[:, :3, 3]
    if array.ndim == 2 and array.shape[1] == 3:
        return array
    raise ValueError(f"{name} must be (N, 3) positions or (N, 4, 4) poses, got shape {array.shape}")


def _poses(name: str, array: np.ndarray) -> np.ndarray:
    return check_shape(array, "N,4,4", name, np.float64)


def _same_length(est: np.ndarray, gt: np.ndarray) -> None:
    if len(est) != len(gt):
        raise ValueError(f"estimate and ground truth must be matched row by row: {len(est)} against {len(gt)} rows")


def umeyama(source: np.ndarray, target: np.ndarray, *, with_scale: bool = False) -> Similarity:
    """The similarity ``(R, t, s)`` minimising ``sum_i |target_i - (s R source_i + t)|^2``.

    ``source``, ``target``: (N, 3) float64 matched points (N >= 2), or (N, 4, 4) poses whose positions
    are used. ``with_scale=False`` keeps ``s = 1`` (SE(3)); ``True`` also solves for the scale (Sim(3)).
    Closed form of Umeyama (1991), ``absolute_orientation.umeyama_alignment``. Points on one line leave
    the rotation about that line free (any of them fits equally well).
    """
    src, dst = _positions("source", source), _positions("target", target)
    _same_length(src, dst)
    if len(src) < 2:
        raise ValueError(f"an alignment needs at least 2 matched positions, got {len(src)}")
    if with_scale and not np.any(src != src[0]):
        raise ValueError("a Sim(3) alignment needs estimated positions that are not all the same point")
    return Similarity(*umeyama_alignment(src, dst, with_scale))


def apply_similarity(alignment: Similarity, poses: np.ndarray) -> np.ndarray:
    """(N, 4, 4) poses ``T_world_body`` moved by the alignment into the other world: rotations
    ``R R_i``, positions ``s R t_i + t`` (the body frame keeps its metric rotation, its position is scaled)."""
    poses = _poses("poses", poses)
    moved = poses.copy()
    moved[:, :3, :3] = alignment.R @ poses[:, :3, :3]
    moved[:, :3, 3] = alignment.apply(poses[:, :3, 3])
    return moved


@dataclass(frozen=True)
class ErrorStats:
    """Summary of non-negative errors: root mean square, mean, median, maximum and count."""

    rmse: float
    mean: float
    median: float
    max: float
    count: int

    def scaled(self, factor: float) -> ErrorStats:
        """The same figures multiplied by ``factor`` (a unit change, e.g. radians to degrees)."""
        return ErrorStats(self.rmse * factor, self.mean * factor, self.median * factor, self.max * factor,
                          self.count)

    def to_dict(self) -> dict[str, float | int]:
        return {"rmse": self.rmse, "mean": self.mean, "median": self.median, "max": self.max, "count": self.count}


def error_stats(errors: np.ndarray) -> ErrorStats:
    """``ErrorStats`` of (M,) errors (NaN figures when M = 0)."""
    errors = np.asarray(errors, dtype=np.float64).ravel()
    if errors.size == 0:
        return ErrorStats(float("nan"), float("nan"), float("nan"), float("nan"), 0)
    return ErrorStats(float(np.sqrt(np.mean(errors**2))), float(np.mean(errors)), float(np.median(errors)),
                      float(np.max(errors)), int(errors.size))


@dataclass(frozen=True)
class AbsoluteError:
    """ATE: the alignment used and (N,) position errors (m) of the aligned estimate, with their stats."""

    alignment: Similarity
    errors: np.ndarray
    stats: ErrorStats


def absolute_trajectory_error(est: np.ndarray, gt: np.ndarray, align: Alignment = "se3") -> AbsoluteError:
    """ATE of an estimated trajectory against the ground truth, after aligning the estimate onto it.

    ``est``, ``gt``: (N, 4, 4) ``T_world_body`` poses or (N, 3) positions, matched row by row.
    ``align``: ``"se3"`` (rotation and translation), ``"sim3"`` (and scale; monocular) or ``"none"``.
    The errors are ``|p_gt_i - (s R p_est_i + t)|`` in metres (the translation part, as evo's APE).
    """
    if align not in ALIGNMENTS:
        raise ValueError(f"unknown alignment {align!r} (use {', '.join(ALIGNMENTS)})")
    p_est, p_gt = _positions("est", est), _positions("gt", gt)
    _same_length(p_est, p_gt)
    alignment = Similarity.identity() if align == "none" else umeyama(p_est, p_gt, with_scale=align == "sim3")
    errors = np.linalg.norm(p_gt - alignment.apply(p_est), axis=1)
    return AbsoluteError(alignment, errors, error_stats(errors))


@dataclass(frozen=True)
class RelativeError:
    """RPE: (M, 2) index pairs ``(i, j)``, their (M,) translation errors (m) and rotation errors (rad),
    with the stats of each."""

    pairs: np.ndarray
    translation: np.ndarray
    rotation: np.ndarray

    @property
    def translation_stats(self) -> ErrorStats:
        return error_stats(self.translation)

    @property
    def rotation_stats(self) -> ErrorStats:
        return error_stats(self.rotation)


def rpe_pairs(gt: np.ndarray, delta: float, unit: DeltaUnit = "frames") -> np.ndarray:
    """(M, 2) int index pairs ``(i, j)``, ``j > i``, over which RPE is taken.

    ``unit="frames"``: ``j = i + delta`` (``delta`` a positive whole number). ``unit="m"``: ``j`` is the
    first row at which the path travelled along the ground truth ``gt`` ((N, 4, 4) poses or (N, 3)
    positions) since row i reaches ``delta`` metres (to within ``PATH_TOLERANCE_M``, so rounding of
    the summed steps does not skip a row), the rule of KITTI's odometry devkit; rows from which the
    rest of the path is shorter have no pair. (evo's ``--all_pairs`` by distance instead takes the row
    whose distance is nearest to ``delta``, so figures over metres differ slightly; over frames they agree.)
    """
    positions = _positions("gt", gt)
    n = len(positions)
    if unit == "frames":
        if delta < 1 or int(delta) != delta:
            raise ValueError(f"an RPE delta in frames must be a whole number >= 1, got {delta}")
        first = np.arange(max(n - int(delta), 0))
        return np.stack([first, first + int(delta)], axis=1)
    if unit != "m":
        raise ValueError(f"unknown RPE delta unit {unit!r} (use {', '.join(DELTA_UNITS)})")
    if not delta > 0:
        raise ValueError(f"an RPE delta in metres must be > 0, got {delta}")
    travelled = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(positions, axis=0), axis=1))])
    second = np.maximum(np.searchsorted(travelled, travelled + delta - PATH_TOLERANCE_M, side="left"),
                        np.arange(1, n + 1))
    keep = second < n
    return np.stack([np.arange(n)[keep], second[keep]], axis=1).astype(np.int64).reshape(-1, 2)


def relative_pose_error(est: np.ndarray, gt: np.ndarray, delta: float = 1, unit: DeltaUnit = "frames",
                        scale: float = 1.0) -> RelativeError:
    """RPE of an estimate against the ground truth over pairs ``delta`` frames or metres apart (``rpe_pairs``).

    ``est``, ``gt``: (N, 4, 4) ``T_world_body``, matched row by row. For each pair ``(i, j)`` the error is
    ``E = (G_i^-1 G_j)^-1 (P_i^-1 P_j)`` with ``G`` the true and ``P`` the estimated poses (estimated
    translations multiplied by ``scale`` first, e.g. the Sim(3) alignment's for a monocular tracker): its
    translation norm (m) and its rotation angle (rad).
    """
    P, G = _poses("est", est).copy(), _poses("gt", gt)
    _same_length(P, G)
    P[:, :3, 3] *= scale
    pairs = rpe_pairs(G, delta, unit)
    i, j = pairs[:, 0], pairs[:, 1]
    motion_est = np.linalg.inv(P[i]) @ P[j]
    motion_gt = np.linalg.inv(G[i]) @ G[j]
    E = np.linalg.inv(motion_gt) @ motion_est
    return RelativeError(pairs, np.linalg.norm(E[:, :3, 3], axis=1), rotation_angles(E[:, :3, :3]))


def associate(stamps_a: np.ndarray, stamps_b: np.ndarray, max_dt_ns: int) -> np.ndarray:
    """One-to-one matches between two stamped sequences: (K, 2) int index pairs ``(i, j)``, sorted by i.

    ``stamps_a``: (N,) int nanoseconds, ``stamps_b``: (M,) int nanoseconds, in any order. Among all pairs
    with ``|a_i - b_j| <= max_dt_ns``, the closest pair is taken first, then the closest of the pairs whose
    stamps are both still free, and so on (ties: lower i, then lower j), as TUM's ``associate.py`` does.
    """
    a, b = check_shape(stamps_a, "N", "stamps_a"), check_shape(stamps_b, "M", "stamps_b")
    if not (np.issubdtype(a.dtype, np.integer) and np.issubdtype(b.dtype, np.integer)):
        raise ValueError(f"stamps must be int nanoseconds, got {a.dtype} and {b.dtype}")
    if max_dt_ns < 0:
        raise ValueError(f"max_dt_ns must be >= 0, got {max_dt_ns}")
    a, b = a.astype(np.int64), b.astype(np.int64)
    order_b = np.argsort(b, kind="stable")
    sorted_b = b[order_b]
    low = np.searchsorted(sorted_b, a - max_dt_ns, side="left")
    high = np.searchsorted(sorted_b, a + max_dt_ns, side="right")
    counts = high - low
    i = np.repeat(np.arange(len(a)), counts)
    starts = np.repeat(low - np.concatenate([[0], np.cumsum(counts)[:-1]]), counts)
    j = order_b[starts + np.arange(counts.sum())]
    dt = np.abs(a[i] - b[j])
    used_a, used_b = np.zeros(len(a), bool), np.zeros(len(b), bool)
    matches = []
    for k in np.lexsort((j, i, dt)):
        if not used_a[i[k]] and not used_b[j[k]]:
            used_a[i[k]] = used_b[j[k]] = True
            matches.append((i[k], j[k]))
    return np.array(sorted(matches), dtype=np.int64).reshape(-1, 2)


@dataclass(frozen=True)
class TrajectoryScore:
    """ATE after the alignment ``align`` and RPE over ``delta`` ``unit`` (estimated translations scaled
    by the alignment's scale) of one matched pair of trajectories."""

    align: str
    delta: float
    unit: str
    ate: AbsoluteError
    rpe: RelativeError

    def to_dict(self) -> dict[str, object]:
        """Plain figures: metres and degrees."""
        a = self.ate.alignment
        return {
            "matched": len(self.ate.errors), "align": self.align, "scale": a.s,
            "alignment": {"R": a.R.tolist(), "t": a.t.tolist(), "s": a.s},
            "ate_m": self.ate.stats.to_dict(),
            "rpe": {"delta": self.delta, "unit": self.unit, "pairs": len(self.rpe.pairs),
                    "translation_m": self.rpe.translation_stats.to_dict(),
                    "rotation_deg": self.rpe.rotation_stats.scaled(float(np.degrees(1.0))).to_dict()},
        }


def score_trajectory(est: np.ndarray, gt: np.ndarray, align: Alignment = "se3", delta: float = 1,
                     unit: DeltaUnit = "frames") -> TrajectoryScore:
    """ATE and RPE of (N, 4, 4) estimated ``T_world_body`` poses against the matched (N, 4, 4) true ones."""
    ate = absolute_trajectory_error(est, gt, align)
    return TrajectoryScore(align, delta, unit, ate, relative_pose_error(est, gt, delta, unit, ate.alignment.s))
