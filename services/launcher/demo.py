"""``artrack demo``: the bundled marker session tracked live over Zenoh, scored against its ground truth.

The job is ``artrack run marker --source recording:recordings/markers.mcap --marker-length
0.05 --depth 8 --record RUN/run.mcap --rerun RUN/run.rrd``: a replay node publishes the
recorded frames, calibration and ground truth (restamped on the recording's clock from the time the first
frame goes out, ``services.runtime.stamps``),
one marker node per camera detects and estimates, and a recorder and a viewer write the run.
This process is the subscribing client: it joins every pose to the ground truth of its frame (by camera and
sequence number), prints a line a second while the run goes on, and a table at the end:
frames, markers tracked, rotation and translation errors, latency from the frame's stamp to
the pose's arrival here (one process hop: the marker node runs in the replay's process, the frame reaching
it by reference, and its poses cross to this client), and the files.

The demo runs on a rig of its own, ``demo-<pid>`` (``artrack demo`` gives that default; a
``--rig`` flag or ``ARTRACK_RIG``, and ``--namespace`` / ``ARTRACK_NAMESPACE``, choose another),
and the recording is replayed onto it whatever rig it was made on: another pipeline on the
default rig can neither feed the demo's marker node nor be counted by its client. A failed
demo says why in one line and exits 1 (or the job's code, e.g. 2 when a node could not
start); one cut short by SIGINT/SIGTERM prints the table of what it did and exits 130.
"""

from __future__ import annotations

import logging
import sys
import threading
from collections import defaultdict
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import TextIO

import numpy as np

from protocol.poses import GroundTruth, Pose
from protocol.tracking_state import TrackingState
from services.bus.pubsub import Inbox, Role
from services.bus.session import BusConfig, close_session, open_session
from services.convert import matrix_from_transform
from services.geometry.evaluation import pose_error
from services.launcher.job import RECORDING_SCHEME, JobExit, JobFile, Recording, build_job, run_job
from services.launcher.tracker import Tracker
from services.recorder.info import summarise

log = logging.getLogger(__name__)

ROOT = Path(__file__).resolve().parents[2]
DEFAULT_RECORDING = ROOT / "recordings" / "markers.mcap"
DEFAULT_RUNS = ROOT / "runs"
MARKER_LENGTH_M = 0.05
"""Side of the markers in the bundled session (the ``markers`` scene's default)."""
DEPTH = 100_000
TRACKED_AT_LEAST = 0.99
FRAME_QUEUE = 8
"""Frames the marker node may queue while busy: a recording should be tracked whole, and on a loaded
machine the node's first frames (OpenCV warming up) or a scheduling hiccup can outlast one frame
period; a queue only fills while the node is behind, so it adds no latency when it keeps up."""


@dataclass
class Scorecard:
    """Poses joined to ground truth: errors per marker view, latencies per pose."""

    truth: dict[tuple[str, int], dict[str, np.ndarray]] = field(default_factory=dict)
    poses: dict[tuple[str, int], dict[str, Pose]] = field(default_factory=lambda: defaultdict(dict))
    latencies_ms: list[float] = field(default_factory=list)
    states: dict[str, int] = field(default_factory=lambda: defaultdict(int))

    def add_truth(self, truth: GroundTruth) -> None:
        self.truth[(truth.header.frame_id, truth.header.seq)] = {
            t.child_frame: matrix_from_transform(t.transform) for t in truth.transforms}

    def add_pose(self, pose: Pose, received_ns: int) -> None:
        self.states[pose.state.value] += 1
        if pose.state is TrackingState.TRACKING:
            self.poses[(pose.header.frame_id, pose.header.seq)][pose.child_frame_id] = pose
            self.latencies_ms.append((received_ns - pose.header.stamp_ns) / 1e6)

    def errors(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Rotation error (deg), translation error (mm) and translation error (% of distance) per scored view."""
        rows = []
        for frame, estimates in self.poses.items():
            known = self.truth.get(frame, {})
            for child, pose in estimates.items():
                if child in known:
                    rotation, translation = pose_error(matrix_from_transform(pose.transform), known[child])
                    rows.append((np.degrees(rotation), translation * 1e3,
                                 100 * translation / np.linalg.norm(known[child][:3, 3])))
        table = np.array(rows).reshape(-1, 3)
        return table[:, 0], table[:, 1], table[:, 2]

    def views(self) -> tuple[int, int]:
        """Marker views in the ground truth, and how many of them got a tracking pose."""
        total = sum(len(known) for known in self.truth.values())
        tracked = sum(len(set(self.poses.get(frame, {})) & set(known)) for frame, known in self.truth.items())
        return total, tracked


def _collect(session, bus: BusConfig, card: Scorecard, stop: threading.Event, out: TextIO) -> None:
    poses = Inbox(session, bus.keys.poses(), Pose, Role.RESULT, depth=DEPTH)
    truths = Inbox(session, bus.keys.every_camera("truth"), GroundTruth, Role.RESULT, depth=DEPTH)
    printed = -1
    try:
        while not stop.is_set() or poses.pending() or truths.pending():
            while (truth := truths.take()) is not None:
                card.add_truth(truth.message)
            received = poses.recv(0.05)
            if received is None:
                continue
            pose = received.message
            card.add_pose(pose, received.received_ns)
            second = pose.header.seq // 30
            if second != printed and pose.state is TrackingState.TRACKING:
                printed = second
                t = pose.transform.translation
                print(f"frame {pose.header.seq:4d}  {pose.header.frame_id}/{pose.child_frame_id:<9} "
                      f"t = ({t[0]:+.3f}, {t[1]:+.3f}, {t[2]:+.3f}) m  rms {pose.quality.reprojection_rms_px:.2f} px"
                      f"  latency {card.latencies_ms[-1]:5.2f} ms", file=out, flush=True)
    finally:
        poses.close()
        truths.close()


def run_demo(bus: BusConfig, recording: Path = DEFAULT_RECORDING, runs: Path = DEFAULT_RUNS,
             out: TextIO = sys.stdout) -> int:
    """Run the demo on ``bus``'s namespace and rig (the recording is replayed there, whatever rig it was
    made on); 0 when the job ended cleanly, wrote its files, and at least ``TRACKED_AT_LEAST`` of the
    ground-truth marker views got a pose (markers cut by the image border may go undetected); else, with
    one line saying why, the job's own ``JobExit`` when it did not end cleanly (130 when SIGINT/SIGTERM
    cut it short: the table shows what was done) and 1 when it did but the run falls short."""
    source = Recording.open(f"{RECORDING_SCHEME}{recording}").moved_to(bus)
    images = next(c for c in summarise(recording).channels if c.key.endswith("/image"))
    camera, frames = images.key.rsplit("/", 2)[-2], images.messages
    session = open_session(bus)
    run_dir = runs / f"demo-{datetime.now():%Y%m%d-%H%M%S}"
    run_dir.mkdir(parents=True, exist_ok=True)
    record, rerun = run_dir / "run.mcap", run_dir / "run.rrd"
    print(f"demo: {recording.name} ({frames} frames, cameras {', '.join(source.cameras)}) -> marker node -> "
          f"this client, on {bus.keys.prefix}; `artrack list` in another shell shows the nodes.", file=out, flush=True)
    card, stop = Scorecard(), threading.Event()
    collector = threading.Thread(target=_collect, args=(session, bus, card, stop, out), daemon=True)
    collector.start()
    try:
        tracker = Tracker.load("marker")
        options = {"marker_length": MARKER_LENGTH_M, "depth": FRAME_QUEUE}
        code = run_job(bus, build_job(tracker, source, options, tracker.flags({}), record, JobFile(rerun)), strict=True)
    finally:
        stop.set()
        collector.join()
        close_session(session)
    played = sum(1 for seen, _ in card.truth if seen == camera)
    _summary(out, f"{played} of {frames}", card, record, rerun)
    if code == JobExit.INTERRUPTED:
        log.warning("demo interrupted after %d of %d frames; the figures above are of those", played, frames)
        return JobExit.INTERRUPTED
    failure = _failure(card, record, rerun, code)
    if failure:
        log.error("demo failed: %s", failure)
        return code or 1
    return 0


def _failure(card: Scorecard, record: Path, rerun: Path, code: int) -> str:
    """Why the demo did not succeed; empty when it did."""
    total, tracked = card.views()
    missing = [str(path) for path in (record, rerun) if not path.is_file()]
    if code == JobExit.FRAMES_LOST:
        return f"{tracked} of {total} marker views tracked, and frames were lost on the way (the line above names " \
               "the nodes that dropped or missed them)"
    if code != 0:
        return f"the job ended with code {code} (its nodes' log lines above say why)"
    if total == 0:
        return "no ground truth reached this client"
    if tracked < TRACKED_AT_LEAST * total:
        return f"{tracked} of {total} marker views tracked, below {TRACKED_AT_LEAST:.0%}"
    if missing:
        return f"not written: {', '.join(missing)}"
    return ""


def _median(values: np.ndarray) -> float:
    return float(np.median(values)) if len(values) else float("nan")


def _summary(out: TextIO, replayed: str, card: Scorecard, record: Path, rerun: Path) -> None:
    rotation, translation_mm, translation_pct = card.errors()
    total, tracked = card.views()
    p50, p99 = np.percentile(card.latencies_ms, [50, 99]) if card.latencies_ms else (float("nan"),) * 2
    p90 = float(np.percentile(rotation, 90)) if len(rotation) else float("nan")
    outcomes = ", ".join(f"{count} {state}" for state, count in card.states.items())
    rows = [
        ("frames", f"{replayed} replayed, {len(card.truth)} with ground truth, {len(card.poses)} with poses"),
        ("markers tracked", f"{tracked} of {total} marker views (poses: {outcomes})"),
        ("rotation error", f"median {_median(rotation):.3f} deg, p90 {p90:.3f} deg"),
        ("translation error", f"median {_median(translation_mm):.2f} mm, {_median(translation_pct):.3f} % of range"),
        ("latency p50 / p99", f"{p50:.2f} / {p99:.2f} ms (frame stamp -> pose here, 1 hop)"),
        ("recorded", str(record)),
        ("rerun", f"{rerun} (open it with `rerun {rerun}`)"),
    ]
    print("\n".join(f"{name:>18}: {value}" for name, value in rows), file=out, flush=True)
