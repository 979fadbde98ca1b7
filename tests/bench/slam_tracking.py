"""Monocular SLAM speed, OpenCV on one thread: tracking per frame, and local mapping per keyframe.

Sequences, their frames read or rendered beforehand (never timed): the synthetic ``room`` at 640x480,
its first ``ROOM_FRAMES`` frames (30 fps stamps), and KITTI 06 frames 0-50 at 1226x370 (10 Hz stamps;
skipped with a line saying so when the data set is absent). Each sequence goes through ``SlamSystem``
(default settings) three times, one after the other:

* ``process``: the mapping in a process of its own (the default), the frames fed at the sequence's own
  rate (a frame that comes due while the one before is still tracked is taken at once), as a camera
  gives them: the mapper gets the wall time between frames that it has in real use;
* ``thread``: the mapping on a thread of the tracker's process, fed the same way;
* ``inline``: ``mapping="inline"``, the frames back to back; a frame that makes a keyframe waits
  for its mapping.

Per variant: ``tracking`` = ``timings_ms["total"]`` less the inline mapping, over every frame (the
initialisation's included), as frames a second (1000 / mean ms) and p50 / p90 ms, and the tracking
thread's CPU ms per frame (``cpu``; less the inline mapping's CPU; the figure least moved by other
work on the machine); p50 / p90 of each stage of ``FrameResult.timings_ms`` over the tracked frames
(``keyframe`` less the inline mapping; ``map_sync``: bringing in the mapping process's changes);
``frames_waited_on_mapping``: frames whose tracking included a keyframe's mapping (inline) or waited at
least ``LOCK_WAIT_MS`` for the map's lock while a mapping thread held it (the map's lock is wrapped for
the run to time the tracking thread's waits; ``lock_wait_ms_max`` the longest; the mapping process
never holds the tracker's lock); ``kept_rate`` whether a fed variant got through the frames at the
sequence's rate (``reached_hz``); frames tracked and lost, keyframes at the end; ``ate_m``: the final
trajectory's ATE (``SlamSystem.trajectory``, Sim(3)-aligned) against the sequence's truth.

Per keyframe of local mapping (``mapping_*`` lines, from the mapper's ``history``): its stage times
(``cull``, ``triangulate``, ``fuse``, ``bundle_adjustment``) and its wall and CPU time per keyframe,
p50 / p90; on the thread the wall time includes the waits for the interpreter lock while tracking
runs, and ``partial`` counts the keyframes that got culling and triangulation only (others waited in
the queue).

``target`` line: tracking at least ``TARGET_FPS`` frames a second at 640x480 with mapping apart (the
default, the process), none of its frames waiting on mapping. ``python -m tests.bench.slam_tracking``
prints the lines.
"""

from __future__ import annotations

import itertools
import json
import threading
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from protocol.tracking_state import TrackingState
from services.geometry.camera import CameraModel
from services.geometry.evaluation import absolute_trajectory_error
from services.slam.system import SlamSystem
from tests.accuracy.slam_sequences import KITTI, kitti, room
from tests.bench.blobs import one_opencv_thread
from tests.bench.link import at_rate
from tests.data import data_root

ROOM_FRAMES = 300
TARGET_FPS = 30.0
LOCK_WAIT_MS = 1.0
STAGES = ("map_sync", "keypoints", "match", "pose", "local_map", "keyframe")
VARIANTS = ("process", "thread", "inline")
MAPPING_STAGES = ("cull", "triangulate", "fuse", "bundle_adjustment")


@dataclass(frozen=True)
class Frames:
    """A sequence read into memory: ``(stamp_ns, image)`` per frame, its ``rate_hz`` and ``truth`` stamp ->
    (4, 4) ``T_world_camera``."""

    name: str
    camera: CameraModel
    frames: list[tuple[int, np.ndarray]]
    rate_hz: float
    truth: dict[int, np.ndarray]


class TimedLock:
    """A re-entrant lock that adds to ``waited_ms`` the milliseconds the ``owner`` thread waited for it."""

    def __init__(self, lock: Any, owner: int):
        self._lock = lock
        self._owner = owner
        self.waited_ms = 0.0

    def acquire(self, blocking: bool = True, timeout: float = -1) -> bool:
        if threading.get_ident() != self._owner:
            return bool(self._lock.acquire(blocking, timeout))
        if self._lock.acquire(blocking=False):
            return True
        started = time.perf_counter()
        got = bool(self._lock.acquire(blocking, timeout))
        self.waited_ms += (time.perf_counter() - started) * 1e3
        return got

    def release(self) -> None:
        self._lock.release()

    def __enter__(self) -> bool:
        return self.acquire()

    def __exit__(self, *exc: object) -> None:
        self.release()


def room_frames(count: int = ROOM_FRAMES) -> Frames:
    sequence = room()
    frames = list(itertools.islice(sequence.frames, count))
    return Frames("room", sequence.camera, [(stamp, image) for stamp, image, _ in frames], 30.0,
                  {stamp: truth for stamp, _, truth in frames})


def kitti_frames() -> Frames | None:
    folder = data_root() / KITTI
    if not folder.is_dir():
        return None
    frames = list(kitti(folder).frames)
    return Frames("kitti", kitti(folder).camera, [(stamp, image) for stamp, image, _ in frames], 10.0,
                  {stamp: truth for stamp, _, truth in frames if truth is not None})


def _p50_p90(values: list[float]) -> dict[str, float]:
    if not values:
        return {"p50_ms": float("nan"), "p90_ms": float("nan")}
    p50, p90 = np.percentile(values, [50, 90])
    return {"p50_ms": round(float(p50), 2), "p90_ms": round(float(p90), 2)}


def run(frames: Frames, mapping: str) -> tuple[dict[str, Any], dict[str, Any]]:
    """One pass of ``frames`` through a fresh system mapping as ``mapping``: the tracking line and the mapping line."""
    system = SlamSystem(frames.camera, mapping=mapping)
    lock = TimedLock(system.map.lock, threading.get_ident())
    system.map.lock = lock  # type: ignore[assignment]
    fed = mapping != "inline"
    tracking, cpu, stages, states = [], [], {stage: [] for stage in STAGES}, []
    waited_inline = waited_lock = 0
    lock_max = 0.0
    started = time.perf_counter()
    try:
        for stamp_ns, image in at_rate(frames.frames, 1.0 / frames.rate_hz if fed else 0.0):
            waited_before, cpu_before = lock.waited_ms, time.thread_time()
            result = system.process(stamp_ns, image)
            timings, mapping_ms = result.timings_ms, result.timings_ms.get("mapping", 0.0)
            lock_wait = lock.waited_ms - waited_before
            lock_max = max(lock_max, lock_wait)
            waited_inline += "mapping" in timings
            waited_lock += lock_wait >= LOCK_WAIT_MS
            tracking.append(timings["total"] - mapping_ms)
            inline_cpu = system._mapper.history[-1].cpu_ms if "mapping" in timings else 0.0
            cpu.append((time.thread_time() - cpu_before) * 1e3 - inline_cpu)
            states.append(result.state)
            if result.state is TrackingState.TRACKING:
                for stage in STAGES:
                    stages[stage].append(timings.get(stage, 0.0) - (mapping_ms if stage == "keyframe" else 0.0))
        elapsed = time.perf_counter() - started
    finally:
        system.close()
    final = [(stamp, T) for stamp, T in system.trajectory() if stamp in frames.truth]
    ate = absolute_trajectory_error(np.array([T for _, T in final]), np.array([frames.truth[t] for t, _ in final]),
                                    "sim3").stats.rmse if len(final) >= 3 else float("nan")
    history = system._mapper.history
    common = {"bench": "slam_tracking", "sequence": frames.name, "width": frames.camera.width,
              "height": frames.camera.height, "frames": len(frames.frames), "variant": mapping, "threads": 1}
    fps = 1e3 / float(np.mean(tracking))
    line = {**common, "figure": "tracking", "fps": round(fps, 1), **_p50_p90(tracking),
            "cpu": _p50_p90(cpu),
            "stages": {stage: _p50_p90(values) for stage, values in stages.items()},
            "tracked": states.count(TrackingState.TRACKING), "lost": states.count(TrackingState.LOST),
            "keyframes": len(system.map.keyframes), "ate_m": round(float(ate), 4),
            "frames_waited_on_mapping": waited_inline + waited_lock,
            "frames_mapped_inline": waited_inline, "lock_wait_ms_max": round(lock_max, 2),
            "lock_wait_ms_total": round(lock.waited_ms, 1)}
    if fed:
        rate = len(frames.frames) / elapsed
        line |= {"rate_hz": frames.rate_hz, "reached_hz": round(rate, 1), "kept_rate": rate >= 0.98 * frames.rate_hz}
    mapping_line = {**common, "figure": "mapping_per_keyframe", "keyframes_mapped": len(history),
                    "wall": _p50_p90([r.wall_ms for r in history]), "cpu": _p50_p90([r.cpu_ms for r in history])}
    if history:
        mapping_line |= {"stages": {stage: _p50_p90([r.stages[stage] for r in history if stage in r.stages])
                                    for stage in MAPPING_STAGES},
                         "partial": sum("fuse" not in r.stages for r in history)}
    return line, mapping_line


def bench_slam_tracking() -> list[dict[str, Any]]:
    lines: list[dict[str, Any]] = []
    with one_opencv_thread():
        sequences = [room_frames(), kitti_frames()]
        for frames in sequences:
            if frames is None:
                lines.append({"bench": "slam_tracking", "sequence": "kitti", "skipped":
                              f"data set {KITTI!r} not found at {data_root() / KITTI} (set ARTRACK_DATA)"})
                continue
            for mapping in VARIANTS:
                lines += run(frames, mapping)
    room_process = lines[0]
    met = room_process["fps"] >= TARGET_FPS and room_process["frames_waited_on_mapping"] == 0
    lines.append({"bench": "slam_tracking", "figure": "target", "sequence": "room", "variant": "process",
                  "fps": room_process["fps"], "frames_waited_on_mapping": room_process["frames_waited_on_mapping"],
                  "target": f">= {TARGET_FPS:.0f} frames/s, no frame waiting on mapping", "met": met})
    return lines


if __name__ == "__main__":
    for line in bench_slam_tracking():
        print(json.dumps(line), flush=True)
