"""Lossless runs of finite sources against the work in one process, idle and with every core busy.

For each tracker, ``artrack run TRACKER --source SCENE --frames N --fps 0 --stamps source --record``
(lossless: the source waits for its slowest node) runs ``RUNS`` times on an idle machine and ``RUNS``
times while ``tests.load.busy`` spins a process on every core. From each recording:

* ``rate_hz``: frames the pipeline got through per second (from the recorder's first image to its
  last result, so a node fed by another's results counts too);
* ``node_rate_hz``: the rate its slowest node could keep alone, 1000 / its processing p50 (its
  last statistics), i.e. the work per frame in one process;
* ``same_results``: whether the results (every key but the inputs, timings, static data and node health, keys taken
  relative to the run's rig) are the same bytes as the first idle run's.

``slam_process`` runs SLAM with its mapping process (the default) ``SLAM_RUNS`` times under load and
counts the runs in which every frame got a pose and the ATE (sim3) stayed within ``SLAM_BAR_M``, and
those whose results are the same bytes as the first run's.
``credits`` runs the marker tracker at ``PACED_FPS`` real-time and lossless, and compares the
latency from a frame's stamp to the recorder's arrival of its poses (p50): the cost of the credits.
"""

from __future__ import annotations

import json
import statistics
import subprocess
import sys
import tempfile
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from mcap.reader import make_reader

from protocol import decode
from protocol.poses import Pose
from protocol.system import NodeStats
from tests.load import busy

ROOT = Path(__file__).resolve().parents[2]
RUNS = 3
SLAM_RUNS = 10
SLAM_FRAMES = 90
SLAM_BAR_M = 0.05
PACED_FPS = 30.0
PACED_FRAMES = 300
TRACKERS = {
    "marker": ("synthetic:markers", 150, ()),
    "stereo": ("synthetic:ir_rig", 120, ()),
    "features": ("synthetic:planar_target", 90, ()),
    "slam_inline": ("synthetic:room", 90, ("--mapping", "inline")),
}
LEFT_OUT = ("/image", "/camera_info", "/truth", "/timings", "/targets")


def _run(tracker: str, source: str, frames: int, options: tuple[str, ...], folder: Path, *extra: str) -> Path:
    out = folder / f"{uuid.uuid4().hex[:8]}.mcap"
    argv = [sys.executable, "-m", "services.cli", "run", tracker.split("_")[0], "--source", source, "--frames",
            str(frames), "--stamps", "source", *options, *extra, "--record", str(out), "--quiet",
            "--rig", f"bench{uuid.uuid4().hex[:6]}"]
    done = subprocess.run(argv, cwd=ROOT, capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(argv)} exited {done.returncode}: {done.stderr[-2000:]}")
    return out


@dataclass
class Recorded:
    """What one run recorded: results by key (relative to the rig), the last result's log time, the images'
    log times, each node's last statistics, and (stamp, log time) of every pose."""

    results: dict[str, list[bytes]] = field(default_factory=dict)
    last_ns: int = 0
    images: list[int] = field(default_factory=list)
    stats: dict[str, NodeStats] = field(default_factory=dict)
    poses: list[tuple[int, int]] = field(default_factory=list)


def _read(path: Path) -> Recorded:
    got = Recorded()
    with open(path, "rb") as f:
        for _, channel, message in make_reader(f).iter_messages(log_time_order=True):
            topic = channel.topic.split("/", 2)[2]  # <namespace>/<rig>/... : each run has a rig of its own
            if topic.endswith("/image"):
                got.images.append(message.log_time)
            elif topic.endswith("/stats"):
                decoded = decode(message.data)
                if isinstance(decoded, NodeStats):
                    got.stats[decoded.node] = decoded
            if topic.startswith(("node/", "tf_static/")) or topic.endswith(LEFT_OUT):
                continue
            got.results.setdefault(topic, []).append(message.data)
            got.last_ns = max(got.last_ns, message.log_time)
            if topic.startswith("pose/"):
                pose = decode(message.data)
                if isinstance(pose, Pose):
                    got.poses.append((pose.header.stamp_ns, message.log_time))
    return got


def _figures(path: Path) -> tuple[dict[str, Any], dict[str, list[bytes]]]:
    got = _read(path)
    span = (got.last_ns - got.images[0]) / 1e9 if got.images else float("nan")
    slowest = max((s.processing_ms_p50 or 0.0) for s in got.stats.values() if s.kind not in ("capture", "recorder"))
    return {"rate_hz": round((len(set(got.images)) - 1) / span, 1) if span else None,
            "node_rate_hz": round(1000.0 / slowest, 1) if slowest else None,
            "lost": sum(s.dropped + s.missing for s in got.stats.values())}, got.results


def bench_tracker(tracker: str, folder: Path) -> list[dict[str, Any]]:
    source, frames, options = TRACKERS[tracker]
    lines, reference = [], None
    for condition in ("idle", "loaded"):
        runs = []
        for _ in range(RUNS):
            if condition == "idle":
                path = _run(tracker, source, frames, options, folder, "--fps", "0")
            else:
                with busy():
                    path = _run(tracker, source, frames, options, folder, "--fps", "0")
            figures, results = _figures(path)
            reference = results if reference is None else reference
            runs.append({**figures, "same_results": results == reference})
            print(f"lossless {tracker} {condition}: {runs[-1]}", file=sys.stderr)
        rates = [r["rate_hz"] for r in runs]
        lines.append({"bench": "lossless", "tracker": tracker, "condition": condition, "frames": frames,
                      "rate_hz_median": statistics.median(rates), "rate_hz_runs": rates,
                      "node_rate_hz_median": statistics.median(r["node_rate_hz"] for r in runs),
                      "lossless_vs_node_rate": round(statistics.median(rates) / statistics.median(
                          r["node_rate_hz"] for r in runs), 3),
                      "frames_lost": sum(r["lost"] for r in runs),
                      "same_results_runs": sum(r["same_results"] for r in runs), "runs": RUNS})
    return lines


def bench_slam_process(folder: Path) -> dict[str, Any]:
    """SLAM with its mapping process, under load: runs where every frame got a pose within the bar, and runs
    whose recorded results are the same bytes as the first run's."""
    good, same, ates, posed = 0, 0, [], []
    reference: dict[str, list[bytes]] | None = None
    with busy():
        for _ in range(SLAM_RUNS):
            path = _run("slam", "synthetic:room", SLAM_FRAMES, (), folder)
            scored = subprocess.run([sys.executable, "-m", "services.cli", "eval", str(path), str(path), "--est-key",
                                     "pose/slam/cam0", "--gt-key", "cam0/truth", "--gt-child", "cam0", "--align",
                                     "sim3", "--json"], cwd=ROOT, capture_output=True, text=True)
            ate = json.loads(scored.stdout)["ate_m"]["rmse"] if scored.returncode == 0 else float("inf")
            results = _read(path).results
            reference = results if reference is None else reference
            same += int(results == reference)
            poses = len(results.get("pose/slam/cam0", []))
            ates.append(round(ate, 4))
            posed.append(poses)
            good += int(poses == SLAM_FRAMES and ate <= SLAM_BAR_M)
            print(f"lossless slam_process loaded: {poses} poses, ATE {ate:.4f} m", file=sys.stderr)
    return {"bench": "lossless", "tracker": "slam_process", "condition": "loaded", "frames": SLAM_FRAMES,
            "runs": SLAM_RUNS, "runs_within_bar": good, "bar_m": SLAM_BAR_M, "ate_m_runs": ates,
            "poses_runs": posed, "same_results_runs": same, "target": f"{SLAM_RUNS} of {SLAM_RUNS}",
            "met": good == SLAM_RUNS}


def bench_credits(folder: Path) -> dict[str, Any]:
    """Marker poses' latency (frame stamp -> recorder) at PACED_FPS, real-time against lossless, alternated."""
    latencies: dict[str, list[float]] = {"realtime": [], "lossless": []}
    for _ in range(RUNS):
        for flow in ("realtime", "lossless"):
            path = _run("marker", "synthetic:markers", PACED_FRAMES, (), folder, "--fps", str(PACED_FPS),
                        "--flow", flow, "--stamps", "wall")
            latencies[flow].append(float(np.percentile([(log - stamp) / 1e6 for stamp, log in _read(path).poses], 50)))
    deltas = [lossless - realtime for realtime, lossless in zip(latencies["realtime"], latencies["lossless"],
                                                                 strict=True)]
    return {"bench": "lossless", "figure": "credits_latency_p50", "fps": PACED_FPS,
            "realtime_p50_ms_runs": [round(v, 2) for v in latencies["realtime"]],
            "lossless_p50_ms_runs": [round(v, 2) for v in latencies["lossless"]],
            "lossless_minus_realtime_p50_ms": round(statistics.median(deltas), 2)}


def bench_lossless() -> list[dict[str, Any]]:
    with tempfile.TemporaryDirectory(prefix="artrack-lossless-") as tmp:
        folder = Path(tmp)
        lines = [line for tracker in TRACKERS for line in bench_tracker(tracker, folder)]
        lines.append(bench_credits(folder))
        lines.append(bench_slam_process(folder))
    return lines
