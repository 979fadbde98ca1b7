"""An estimated trajectory scored against the true one: match, align, ATE and RPE, as text or JSON.

What ``artrack eval`` prints. Rows are paired by stamp, frame number or index (``pairing.pair``;
trajectories that hardly overlap are refused); the estimate is aligned onto the ground truth with Umeyama
(``se3``, ``sim3`` or ``none``); ATE is the position error after alignment, RPE the error of the
motion over ``delta`` frames or metres (estimated translations scaled by the Sim(3) scale).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from services.geometry.evaluation import Alignment, DeltaUnit, ErrorStats, TrajectoryScore, score_trajectory
from services.recorder.pairing import PairBy, Pairing, pair
from services.recorder.trajectories import Trajectory, TrajectoryError

__all__ = ["DEFAULT_MAX_DT_S", "Evaluation", "evaluate", "format_evaluation"]

DEFAULT_MAX_DT_S = 0.02
"""Largest stamp difference of a matched pair by default (TUM's associate.py uses the same)."""


@dataclass(frozen=True)
class Evaluation:
    """Both trajectories, how their rows were paired, the largest stamp difference allowed (ns) and
    the score of the paired rows."""

    est: Trajectory
    gt: Trajectory
    pairing: Pairing
    max_dt_ns: int
    score: TrajectoryScore

    @property
    def pairs(self) -> np.ndarray:
        """(K, 2) int64 paired rows ``(i_est, i_gt)``."""
        return self.pairing.rows

    def to_dict(self) -> dict[str, object]:
        return {"est": self.est.name, "gt": self.gt.name, "est_poses": len(self.est), "gt_poses": len(self.gt),
                "matched_by": self.pairing.by, "matched_note": self.pairing.note, "max_dt_s": self.max_dt_ns / 1e9,
                **self.score.to_dict()}


def evaluate(est: Trajectory, gt: Trajectory, *, align: Alignment = "se3", delta: float = 1,
             unit: DeltaUnit = "frames", max_dt_s: float = DEFAULT_MAX_DT_S, by: PairBy = "auto") -> Evaluation:
    """Pair ``est`` with ``gt`` ``by`` stamp, frame number or index (``pairing.pair``) and score the paired
    rows; ``TrajectoryError`` when they cannot be paired or hardly overlap."""
    if not max_dt_s >= 0:
        raise TrajectoryError(f"--max-dt must be >= 0 seconds, got {max_dt_s}")
    max_dt_ns = round(max_dt_s * 1e9)
    pairing = pair(est, gt, by, max_dt_ns)
    score = score_trajectory(est.poses[pairing.rows[:, 0]], gt.poses[pairing.rows[:, 1]], align, delta, unit)
    return Evaluation(est, gt, pairing, max_dt_ns, score)


def _figures(stats: ErrorStats, digits: int) -> str:
    if stats.count == 0:
        return "n/a (no pairs)"
    return "  ".join(f"{name} {value:.{digits}f}" for name, value in
                     (("rmse", stats.rmse), ("mean", stats.mean), ("median", stats.median), ("max", stats.max)))


def format_evaluation(evaluation: Evaluation) -> str:
    """The figures as a few lines of text: metres and degrees."""
    score = evaluation.score
    pairing = evaluation.pairing
    how = {"stamp": f"by stamp within {evaluation.max_dt_ns / 1e9:g} s", "frame": "by frame number",
           "index": "by index"}[pairing.by] + (f" ({pairing.note})" if pairing.note else "")
    alignment = score.align + (f", scale {score.ate.alignment.s:.6f}" if score.align == "sim3" else "")
    rpe = score.rpe
    unit = "m" if score.unit == "m" else "frame" if score.delta == 1 else "frames"
    lines = [
        f"matched      {len(evaluation.pairs)} poses ({len(evaluation.est)} estimated, {len(evaluation.gt)} true) "
        f"{how}",
        f"alignment    {alignment}",
        f"ATE (m)      {_figures(score.ate.stats, 6)}",
        f"RPE over {score.delta:g} {unit}: {len(rpe.pairs)} pairs",
        f"  trans (m)  {_figures(rpe.translation_stats, 6)}",
        f"  rot (deg)  {_figures(rpe.rotation_stats.scaled(math.degrees(1.0)), 4)}",
    ]
    return "\n".join(lines)
