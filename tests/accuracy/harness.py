"""Any tracker's recording scored against the ground truth it recorded, with ATE and RPE.

A run recorded with ``--record`` holds the tracker's poses (``pose/...``) and, for synthetic
scenes and their recordings, the truth of every frame (``<camera>/truth``, stamped as the frame
the poses derive from, so they match at ``max_dt_s=0``). ``score_recording`` reads both as
``artrack eval`` does and returns its ``Evaluation`` (``len(evaluation.gt)``: the frames whose
truth has the target, ``len(evaluation.pairs)``: those the tracker gave a pose for).
"""

from __future__ import annotations

from pathlib import Path

from services.geometry.evaluation import Alignment, DeltaUnit
from services.recorder.scoring import Evaluation, evaluate
from services.recorder.trajectories import read_recording


def score_recording(path: Path | str, pose_key: str, truth_key: str, *, child: str | None = None,
                    align: Alignment = "none", delta: float = 1, unit: DeltaUnit = "frames",
                    max_dt_s: float = 0.0) -> Evaluation:
    """The poses on ``pose_key`` (of ``child`` only, when named) against the truth of ``child`` on ``truth_key``.

    Keys are absolute or relative to the recording's ``namespace/rig``. ``align`` defaults to none: a
    tracker that reports in the truth's own frames (a marker in its camera's frame) is scored as it is;
    ``se3`` / ``sim3`` for trackers with their own world (SLAM).
    """
    est = read_recording(path, pose_key, child)
    gt = read_recording(path, truth_key, child)
    return evaluate(est, gt, align=align, delta=delta, unit=unit, max_dt_s=max_dt_s)

