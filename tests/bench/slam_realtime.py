"""Monocular SLAM in real time: does the node keep up with a camera's rate, frame for frame?

Two sequences at their own rate, each run through ``artrack run slam --flow realtime --record R.mcap``
(a capture node, the SLAM node with its mapping process, the default, and a recorder; frames
latest-wins, so a node that falls behind drops them):

* ``room``: the synthetic ``room`` scene, 640x480, ``ROOM_FRAMES`` frames at 30 fps (rendered by the
  capture node as they go out);
* ``kitti``: the KITTI 06 excerpt (``tests.accuracy.slam_sequences.KITTI``, 1226x370, its 51 frames at
  10 fps; a ``skipped`` line when the data set is absent).

Each sequence runs ``RUNS`` times on the machine as it is (``idle``) and ``RUNS`` times while
``tests.load.busy`` spins a process on every core (``loaded``). From each recording: the frames the capture
sent (images recorded), the SLAM node's frames dropped (its last ``NodeStats``: frames that came while one was
being processed and the queue was full), the frames without a pose before the first tracked one
(initialisation) and after it, its poses and those ``tracking``, their ATE (RMSE after a Sim(3) alignment,
against the truth the room records with its frames or KITTI's ``poses.txt`` by frame number) and that of the
final trajectory the node publishes as it stops, and the
machine's 1-minute load average before and after (the machine is shared: its load says what "idle" was), and
the smallest, median and largest gap between two frames' stamps. One JSON line per run, then one per sequence
and condition: runs with 0 frames dropped out of ``RUNS`` (the target: all of them), the SLAM node's
processing p50 / p99 (its stats, ms) per run, and the ATE's min / median / max over the runs.

``python -m tests.bench.slam_realtime [--runs N] [--sequences room kitti] [--conditions idle loaded]
[--processes given|separate|single] [--flow realtime|lossless] [--nice N]`` prints the lines (``--runs`` lowers
the ten runs for a quick look; ``--flow lossless``: the same runs lossless, every frame taken, stamped on the
source's clock; ``--nice``: the job's nodes but the recorder at that priority, ``artrack run --nice``);
``python -m tests.bench slam_realtime`` runs the default.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import uuid
from collections.abc import Iterator
from contextlib import AbstractContextManager, nullcontext
from pathlib import Path
from typing import Any

import numpy as np
from mcap.reader import make_reader

from protocol import decode
from protocol.maps import Trajectory
from protocol.poses import GroundTruth, Pose
from protocol.system import NodeStats
from protocol.tracking_state import TrackingState
from services.convert import matrix_from_transform
from services.geometry.evaluation import absolute_trajectory_error
from services.recorder.trajectories import read_kitti
from tests.accuracy.slam_sequences import KITTI
from tests.data import data_root
from tests.load import busy

ROOT = Path(__file__).resolve().parents[2]
RUNS = 10
ROOM_FRAMES = 300
CONDITIONS = ("idle", "loaded")


def sources() -> dict[str, tuple[str, ...] | None]:
    """Each sequence's source flags (None when its data set is absent)."""
    kitti = data_root() / KITTI / "image_0"
    return {"room": ("--source", "synthetic:room", "--frames", str(ROOM_FRAMES), "--fps", "30"),
            "kitti": ("--source", f"images:{kitti}", "--fps", "10") if kitti.is_dir() else None}


def truths() -> dict[str, dict[int, np.ndarray] | None]:
    """Each sequence's true ``T_world_camera`` by frame sequence number where the recording does not carry
    it (the KITTI excerpt's ``poses.txt``; the room's truth is recorded with its frames)."""
    poses = data_root() / KITTI / "poses.txt"
    return {"room": None, "kitti": dict(enumerate(read_kitti(poses).poses)) if poses.is_file() else None}


def run_once(flags: tuple[str, ...], folder: Path, truth: dict[int, np.ndarray] | None = None,
             flow: str = "realtime") -> dict[str, Any]:
    """One run of the SLAM tracker with a recorder (real-time unless ``flow`` says otherwise); its figures from the
    recording (``truth``: true poses by sequence number when the recording has none)."""
    out = folder / f"{uuid.uuid4().hex[:8]}.mcap"
    argv = [sys.executable, "-m", "services.cli", "run", "slam", *flags, "--flow", flow, "--record", str(out),
            "--quiet", "--rig", f"bench{uuid.uuid4().hex[:6]}"]
    done = subprocess.run(argv, cwd=ROOT, capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(argv)} exited {done.returncode}: {done.stderr[-2000:]}")
    figures = read_run(out, truth)
    out.unlink()
    return figures


def read_run(path: Path, truth: dict[int, np.ndarray] | None = None) -> dict[str, Any]:
    """Frames sent (images recorded), the SLAM node's dropped frames and processing p50 / p99 (its last
    stats), its poses and how many of them were tracking, and the ATE (m, RMSE after a Sim(3) alignment)
    of the tracking poses against the recorded truth of ``cam0`` (or ``truth`` by sequence number)."""
    images, poses, tracked = 0, 0, 0
    stamps: list[int] = []
    sent: set[int] = set()
    posed: dict[int, bool] = {}
    estimated: dict[int, np.ndarray] = {}
    final: dict[int, np.ndarray] = {}
    recorded: dict[int, np.ndarray] = {}
    stats: NodeStats | None = None
    with open(path, "rb") as f:
        for _, channel, message in make_reader(f).iter_messages(log_time_order=True):
            topic = channel.topic
            if topic.endswith("/image"):
                images += 1
                header = decode(message.data).header
                sent.add(header.seq)
                stamps.append(header.stamp_ns)
            elif topic.endswith("/stats"):
                decoded = decode(message.data)
                if isinstance(decoded, NodeStats) and decoded.kind == "slam":
                    stats = decoded
            elif "/pose/slam/" in f"/{topic}":
                pose = decode(message.data)
                if isinstance(pose, Pose):
                    poses += 1
                    tracked += pose.state is TrackingState.TRACKING
                    posed[pose.header.seq] = pose.state is TrackingState.TRACKING
                    if pose.state is TrackingState.TRACKING:
                        estimated[pose.header.seq] = matrix_from_transform(pose.transform)
            elif topic.endswith("/trajectory"):
                trajectory = decode(message.data)
                if isinstance(trajectory, Trajectory):
                    final = dict(zip(trajectory.seqs.tolist(), trajectory.poses, strict=True))
            elif topic.endswith("cam0/truth"):
                known = decode(message.data)
                if isinstance(known, GroundTruth):
                    recorded.update((known.header.seq, matrix_from_transform(t.transform))
                                    for t in known.transforms if t.child_frame == "cam0")
    if stats is None:
        raise RuntimeError(f"{path}: no statistics of the slam node were recorded")
    first_tracked = min((seq for seq, tracking in posed.items() if tracking), default=max(sent, default=0) + 1)
    unposed = sent - set(posed)
    return {"sent": images, "dropped": stats.dropped + stats.missing,
            "unposed_before_tracking": sum(seq < first_tracked for seq in unposed),
            "unposed_after": sum(seq > first_tracked for seq in unposed), "poses": poses, "tracked": tracked,
            "node_p50_ms": round(stats.processing_ms_p50 or 0.0, 1),
            "node_p99_ms": round(stats.processing_ms_p99 or 0.0, 1),
            "ate_m": _ate_m(estimated, recorded if truth is None else truth),
            "final_ate_m": _ate_m(final, recorded if truth is None else truth),
            "stamp_gap_ms": _spread(list(np.diff(np.sort(stamps)) / 1e6))}


def _ate_m(estimated: dict[int, np.ndarray], truth: dict[int, np.ndarray]) -> float | None:
    """ATE RMSE (m) after a Sim(3) alignment of the poses of the sequence numbers both hold (None under three)."""
    both = sorted(set(estimated) & set(truth))
    if len(both) < 3:
        return None
    error = absolute_trajectory_error(np.array([estimated[seq] for seq in both]),
                                      np.array([truth[seq] for seq in both]), "sim3")
    return round(float(error.stats.rmse), 4)


def _condition(name: str) -> AbstractContextManager[Any]:
    return busy() if name == "loaded" else nullcontext()


def runs(sequence: str, flags: tuple[str, ...], condition: str, count: int, folder: Path,
         layout: str = "given", truth: dict[int, np.ndarray] | None = None,
         flow: str = "realtime", nice: int | None = None) -> Iterator[dict[str, Any]]:
    """``count`` runs of one sequence under one condition: a line per run, then the summary line (with the
    ATE's min / median / max over the runs)."""
    common = {"bench": "slam_realtime", "sequence": sequence, "condition": condition, "processes": layout,
              "flow": flow, **({} if nice is None else {"nice": nice})}
    lines = []
    for run in range(count):
        load_before = os.getloadavg()[0]
        with _condition(condition):
            figures = run_once(flags, folder, truth, flow)
        figures |= {"loadavg_1m_before": round(load_before, 2), "loadavg_1m_after": round(os.getloadavg()[0], 2)}
        lines.append(figures)
        print(f"slam_realtime {sequence} {condition} {run + 1}/{count}: {figures}", file=sys.stderr, flush=True)
        yield {**common, "run": run + 1, **figures}
    yield {**common, "runs": count, "runs_without_drops": sum(line["dropped"] == 0 for line in lines),
           "dropped_runs": [line["dropped"] for line in lines], "tracked_runs": [line["tracked"] for line in lines],
           "sent_runs": [line["sent"] for line in lines],
           "node_p50_ms_runs": [line["node_p50_ms"] for line in lines],
           "node_p99_ms_runs": [line["node_p99_ms"] for line in lines],
           "ate_m_min_median_max": _spread([line["ate_m"] for line in lines]),
           "final_ate_m_min_median_max": _spread([line["final_ate_m"] for line in lines]),
           "target": f"0 dropped in {count} of {count}",
           "met": all(line["dropped"] == 0 for line in lines)}


def _spread(values: list[float | None]) -> list[float] | None:
    """``[min, median, max]`` of the values given (None when there is none)."""
    known = [value for value in values if value is not None]
    return [round(float(f(known)), 4) for f in (np.min, np.median, np.max)] if known else None


def bench_slam_realtime(count: int = RUNS, sequences: tuple[str, ...] = ("room", "kitti"),
                        conditions: tuple[str, ...] = CONDITIONS, layout: str = "given",
                        flow: str = "realtime", nice: int | None = None) -> list[dict[str, Any]]:
    lines: list[dict[str, Any]] = []
    known = truths()
    with tempfile.TemporaryDirectory(prefix="artrack-slam-realtime-") as tmp:
        for sequence in sequences:
            flags = sources()[sequence]
            if flags is None:
                lines.append({"bench": "slam_realtime", "sequence": sequence,
                              "skipped": f"data set {KITTI!r} not found at {data_root() / KITTI}"})
                continue
            for condition in conditions:
                asked = (*flags, "--processes", layout, *(() if nice is None else ("--nice", str(nice))))
                lines += runs(sequence, asked, condition, count, Path(tmp), layout, known[sequence], flow, nice)
    return lines


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m tests.bench.slam_realtime", description=__doc__.split("\n")[0])
    parser.add_argument("--runs", type=int, default=RUNS, help=f"runs per sequence and condition (default {RUNS})")
    parser.add_argument("--sequences", nargs="+", choices=("room", "kitti"), default=["room", "kitti"])
    parser.add_argument("--conditions", nargs="+", choices=CONDITIONS, default=list(CONDITIONS))
    parser.add_argument("--processes", choices=("given", "separate", "single"), default="given",
                        help="how the nodes share processes (artrack run --processes; default: the template's)")
    parser.add_argument("--flow", choices=("realtime", "lossless"), default="realtime",
                        help="artrack run --flow (default realtime: frames latest-wins)")
    parser.add_argument("--nice", type=int, help="artrack run --nice: the priority of every node but the recorder")
    args = parser.parse_args(argv)
    for line in bench_slam_realtime(args.runs, tuple(args.sequences), tuple(args.conditions), args.processes,
                                    args.flow, args.nice):
        print(json.dumps(line), flush=True)


if __name__ == "__main__":
    main()
