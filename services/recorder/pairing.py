"""Which rows of an estimated and a true trajectory are the same instant: by stamp, frame number or index.

``pair`` matches rows one to one (``geometry.evaluation.associate``, closest first):

* ``stamp``: stamps at most ``max_dt_ns`` apart, when both trajectories have stamps.
* ``frame``: equal frame numbers, when both have them (a KITTI file's rows, a recording's ``header.seq``).
* ``index``: row i of each, when asked for; or, when asked for nothing, when neither stamps nor frame
  numbers are on both sides (a TUM file against a KITTI file without ``times.txt``) and the two hold
  as many poses. The pairing then carries a ``note`` saying so.
* ``auto``: by stamp when both have stamps that pair well enough, else by frame number when both
  have frame numbers that pair well enough, else by index as above.

Well enough: at least ``MIN_PAIRS`` pairs and at least ``MIN_SHARE`` of the estimate's poses. Two
trajectories that pair worse (unrelated runs, stamps of different clocks, counts that differ with
nothing to pair by) are refused with a ``TrajectoryError`` whose one line says the counts: a score
of a few rows, or of rows of other instants, says nothing of the estimate.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

from services.geometry.evaluation import associate
from services.recorder.trajectories import Trajectory, TrajectoryError

__all__ = ["MIN_PAIRS", "MIN_SHARE", "PAIR_BY", "PairBy", "Pairing", "pair", "pairs_needed"]

PairBy = Literal["auto", "stamp", "frame", "index"]
PAIR_BY: tuple[str, ...] = ("auto", "stamp", "frame", "index")
MIN_PAIRS = 3
"""Fewest pairs a score is made of (a Sim(3) alignment needs three positions)."""
MIN_SHARE = 0.5
"""Smallest share of the estimate's poses that must pair with a true pose."""
WHAT = {"stamp": "stamp", "frame": "frame number", "index": "index"}
CARRIES = {(True, True): "stamps and frame numbers", (True, False): "stamps but no frame numbers",
           (False, True): "frame numbers but no stamps", (False, False): "neither stamps nor frame numbers"}
"""What a trajectory carries, by (has stamps, has frame numbers)."""


@dataclass(frozen=True)
class Pairing:
    """(K, 2) int64 ``rows`` ``(i_est, i_gt)`` sorted by ``i_est``, found ``by`` ``stamp``, ``frame`` or
    ``index``; ``note`` says why by index when that was not asked for (empty otherwise)."""

    rows: np.ndarray
    by: str
    note: str = ""


def pairs_needed(est: Trajectory) -> int:
    """Fewest pairs an estimate of ``len(est)`` poses is scored on: ``MIN_SHARE`` of them, at least ``MIN_PAIRS``."""
    return max(MIN_PAIRS, math.ceil(MIN_SHARE * len(est)))


def _labels(trajectory: Trajectory, by: str) -> np.ndarray | None:
    """(N,) int64 stamps (ns) or frame numbers of ``trajectory``; None when it has none."""
    return trajectory.stamps_ns if by == "stamp" else trajectory.frames


def _carries(trajectory: Trajectory) -> str:
    """What ``trajectory`` can be paired by, in words."""
    return CARRIES[(trajectory.stamps_ns is not None, trajectory.frames is not None)]


def _by_index(est: Trajectory, gt: Trajectory) -> np.ndarray:
    rows = np.arange(min(len(est), len(gt)), dtype=np.int64)
    return np.stack([rows, rows], axis=1)


def pair(est: Trajectory, gt: Trajectory, by: PairBy = "auto", max_dt_ns: int = 0) -> Pairing:
    """The rows of ``est`` and ``gt`` that are the same instant, found ``by`` (see the module's text);
    ``max_dt_ns``: the largest stamp difference of a pair. Raises ``TrajectoryError`` when the two
    cannot be paired that way or pair on fewer than ``pairs_needed(est)`` rows."""
    if by not in PAIR_BY:
        raise TrajectoryError(f"cannot pair by {by!r} (use {', '.join(PAIR_BY)})")
    needed = pairs_needed(est)
    overlap = f"{est.name} ({len(est)} poses) and {gt.name} ({len(gt)} poses) hardly overlap: "
    at_least = f"at least {needed} needed (half the estimate's poses, and no fewer than {MIN_PAIRS})"
    if by == "index":
        rows = _by_index(est, gt)
        if len(rows) < needed:
            raise TrajectoryError(f"{overlap}{len(rows)} paired by index, {at_least}")
        return Pairing(rows, "index")
    tried = []
    for method in ("stamp", "frame") if by == "auto" else (by,):
        labels_est, labels_gt = _labels(est, method), _labels(gt, method)
        if labels_est is None or labels_gt is None:
            if by != "auto":
                lacking = est if labels_est is None else gt
                raise TrajectoryError(f"cannot pair by {WHAT[method]}: {lacking.name} has {_carries(lacking)}")
            continue
        rows = associate(labels_est, labels_gt, max_dt_ns if method == "stamp" else 0)
        if len(rows) >= needed:
            return Pairing(rows, method)
        within = f" within {max_dt_ns / 1e9:g} s" if method == "stamp" else ""
        tried.append(f"{len(rows)} paired by {WHAT[method]}{within}")
    if tried:
        raise TrajectoryError(f"{overlap}{' and '.join(tried)}, {at_least}")
    carries = f"{est.name} has {_carries(est)}, {gt.name} {_carries(gt)}"
    if len(est) != len(gt):
        raise TrajectoryError(f"nothing to pair {est.name} ({len(est)} poses) and {gt.name} ({len(gt)} poses) by: "
                              f"{carries}, and their counts differ (a recording's poses carry frame numbers, a "
                              "times.txt beside a KITTI file gives it stamps; --match-by index only if row i of "
                              "each is the same instant)")
    return Pairing(_by_index(est, gt), "index", f"{carries}: row i of each taken as the same instant")
