"""Trackers run as users run them, ``artrack run TRACKER``, with their nodes grouped into processes three ways.

Each run is a real job (``artrack run TRACKER --source synthetic:SCENE --fps RATE --frames N --flow realtime
--processes LAYOUT``) on a private router, with this process as a client app following every pose
(``tests.bench.live``): ``given`` is the template's grouping (the default), ``separate`` every node in its own
process, ``single`` every node but the recorder in one. Per run: latency per frame (its stamp, taken by the
capture as the frame goes out, to the arrival here of its last pose) p50 / p99 after ``WARMUP`` frames;
``updates_per_s``, frames whose poses arrived per second of sending; ``dropped``, frames sent that some node
never processed (the nodes' final ``NodeStats``: frames dropped by latest-wins plus frames missing); each
process's CPU while the frames flowed (``cores``, 1.0 = one busy core, by process name).

* ``stereo``: the ``ir_rig`` scene (640x480, 3 bodies), two cameras at 240 Hz, the default grouping for
  ``TARGET_SECONDS`` (target: 240 updates/s, 0 dropped, p50 <= 3 ms, p99 <= 6 ms), the two others for
  ``STEREO_SECONDS`` each; then, with the default grouping, three cameras at 240 Hz and two at 360 Hz.
* ``marker``: the ``markers`` scene at 60 fps with a recorder, against the same work in one process paced
  at 60 fps (``tests.bench.markers.in_process``, its markers' side given, as the scene renders them and the job
  is told): target 0 dropped, p50 <= in-process p50 + 0.5 ms.
* ``features``: the ``planar_target`` scene 640x480 at 60 fps (incremental tracking), against the node's work
  in one process paced alike (``tests.bench.features_bus.in_process``): target 0 dropped, p50 <= in-process
  + 0.5 ms.

* ``priority`` (not in the default run): the stereo target's job for ``STEREO_SECONDS``, ``ROUNDS`` times idle
  and under ``tests.load.busy()`` (a spinning process on each core), each without and with ``--nice NICE``
  (every node but the recorder ahead of the rest; a ``skipped`` line where this user may not raise a
  priority).

``python -m tests.bench.layouts [stereo|marker|features|priority ...] [--seconds S]`` prints the lines.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from protocol.system import NodeStats
from services.bus.pubsub import Listener
from services.launcher.scheduling import may_raise_priority
from tests.bench import features_bus, markers
from tests.bench.figures import host
from tests.bench.link import cpu_seconds
from tests.bench.live import LiveBus
from tests.load import busy

WARMUP = 20
PRERENDER = 240
STEREO_SECONDS = 20.0
TARGET_SECONDS = 60.0
SECONDS = 10.0
LAYOUTS = ("given", "separate", "single")
DONE_S = 120.0
STEREO_TARGET = {"updates_per_s": 240.0, "p50_ms": 3.0, "p99_ms": 6.0}
OVERHEAD_TARGET_MS = 0.5
ROUNDS = 2
NICE = -10


def children(pid: int) -> list[int]:
    """The child processes of ``pid`` (every thread's), from /proc."""
    found: list[int] = []
    for task in Path(f"/proc/{pid}/task").glob("*"):
        try:
            found += [int(child) for child in (task / "children").read_text().split()]
        except (OSError, ValueError):
            continue
    return found


def run_job(tracker: str, scene: str, rate: float, frames: int, layout: str, *extra: str) -> dict[str, Any]:
    """One ``artrack run`` of ``tracker`` on ``scene`` at ``rate`` for ``frames`` frames, grouped by ``layout``; the
    scene's first ``PRERENDER`` instants rendered before the run and cycled, so that the source costs what a
    camera does, not a renderer's work."""
    with LiveBus(f"{tracker}_probe") as live:
        last: dict[str, NodeStats] = {}
        stats = Listener(live.session, f"{live.bus.keys.prefix}/node/*/stats", NodeStats,
                         lambda received: last.__setitem__(received.message.node, received.message))
        job = live.start([sys.executable, "-m", "services.cli", "run", tracker, "--source", f"synthetic:{scene}",
                          "--fps", str(rate), "--frames", str(frames), "--prerender", str(PRERENDER),
                          "--flow", "realtime", "--processes", layout, "--quiet", *extra],
                         stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        cpu: dict[int, tuple[float, float, float]] = {}
        deadline = time.monotonic() + DONE_S
        while job.poll() is None and time.monotonic() < deadline:
            now = time.monotonic()
            for pid in children(job.pid):
                try:
                    used = cpu_seconds(pid)
                except OSError:
                    continue
                first = cpu.get(pid, (now, used, used))
                cpu[pid] = (first[0], first[1], used) if live.arrived else (now, used, used)
            time.sleep(0.25)
        if job.poll() is None:
            job.kill()
        _, errors = job.communicate()
        stats.close()
        if job.returncode != 0:
            raise RuntimeError(f"artrack run {tracker} exited {job.returncode}: {errors[-2000:]}")
        latencies = live.latencies(WARMUP)
        seqs = {update.pose.header.seq for update in live.arrived}
    sent = last["capture"].published if "capture" in last else 0
    frame_nodes = [s for s in last.values() if s.kind not in ("capture", "recorder")]
    by_pid: dict[int, list[str]] = {}
    for s in last.values():
        by_pid.setdefault(s.pid, []).append(s.node)
    seconds = frames / rate
    cores = {"+".join(by_pid.get(pid, [str(pid)])): round((end - start) / seconds, 2)
             for pid, (_, start, end) in cpu.items()}
    p50, p99 = np.percentile(latencies, [50, 99]) if latencies else (float("nan"), float("nan"))
    return {"tracker": tracker, "scene": scene, "rate_hz": rate, "frames": frames, "layout": layout,
            "processes": len(by_pid), "p50_ms": round(float(p50), 3), "p99_ms": round(float(p99), 3),
            "updates_per_s": round(len(seqs) * rate / frames, 1),
            "dropped": sum(s.dropped + s.missing for s in frame_nodes), "capture_messages": sent,
            "node_dropped": {s.node: s.dropped for s in frame_nodes},
            "node_p50_ms": {s.node: s.processing_ms_p50 for s in frame_nodes},
            "node_latency_p50_ms": {s.node: s.latency_ms_p50 for s in frame_nodes}, "cores": cores}


def bench_stereo_layouts(seconds: float = STEREO_SECONDS) -> list[dict[str, Any]]:
    """The target run (default grouping, two cameras, 240 Hz, ``TARGET_SECONDS``), the other groupings for
    ``seconds`` each, then three cameras at 240 Hz and two at 360 Hz."""
    target = run_job("stereo", "ir_rig", 240.0, int(240 * max(seconds, TARGET_SECONDS)), "given")
    target["target"] = STEREO_TARGET
    target["met"] = (target["dropped"] == 0 and target["updates_per_s"] >= STEREO_TARGET["updates_per_s"] * 0.99
                     and target["p50_ms"] <= STEREO_TARGET["p50_ms"] and target["p99_ms"] <= STEREO_TARGET["p99_ms"])
    lines = [target] + [run_job("stereo", "ir_rig", 240.0, int(240 * seconds), layout) for layout in LAYOUTS[1:]]
    lines.append({**run_job("stereo", "ir_rig", 240.0, int(240 * seconds), "given", "--scene-option",
                            "camera_count=3"), "cameras": 3})
    lines.append(run_job("stereo", "ir_rig", 360.0, int(360 * seconds), "given"))
    return [{"bench": "layouts", **line} for line in lines]


def _against(in_process: dict[str, float], lines: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Each line with its p50 over the in-process p50, and whether it meets the overhead target."""
    for line in lines:
        line["in_process_p50_ms"] = in_process["p50_ms"]
        line["over_in_process_ms"] = round(line["p50_ms"] - in_process["p50_ms"], 3)
        line["met"] = line["dropped"] == 0 and line["over_in_process_ms"] <= OVERHEAD_TARGET_MS
    return [{"bench": "layouts", **line} for line in lines]


def bench_marker_layouts(seconds: float = SECONDS) -> list[dict[str, Any]]:
    frames = int(60 * seconds)
    with tempfile.TemporaryDirectory(prefix="layouts") as folder:
        lines = [run_job("marker", "markers", 60.0, frames, layout, "--record", str(Path(folder) / f"{layout}.mcap"))
                 for layout in ("given", "separate")]
    paced = markers.in_process(markers.DetectorSettings(marker_length=markers.MARKER_LENGTH), 1 / 60)
    return _against(paced, lines)


def bench_features_layouts(seconds: float = SECONDS) -> list[dict[str, Any]]:
    frames = int(60 * seconds)
    size = ("--scene-option", f"width={features_bus.WIDTH}", "--scene-option", f"height={features_bus.HEIGHT}")
    lines = [run_job("features", "planar_target", 60.0, frames, layout, *size) for layout in ("given", "separate")]
    paced = features_bus.in_process(1 / 60)
    return _against({"p50_ms": paced["p50_ms"]}, lines)


def bench_stereo_priority(seconds: float = STEREO_SECONDS) -> list[dict[str, Any]]:
    """The stereo target's job ``ROUNDS`` times idle and busy, each without and with ``--nice NICE``, alternated."""
    if not may_raise_priority(NICE):
        return [{"bench": "layouts", "variant": "priority", "skipped": f"this user may not give nice {NICE}"}]
    frames = int(240 * seconds)
    lines = []
    for _ in range(ROUNDS):
        for load in ("idle", "busy"):
            for extra in ((), ("--nice", str(NICE))):
                with busy() if load == "busy" else contextlib.nullcontext():
                    found = run_job("stereo", "ir_rig", 240.0, frames, "given", *extra)
                lines.append({"condition": load + (f", nice {NICE}" if extra else ""), **found})
    return [{"bench": "layouts", "variant": "priority", **line} for line in lines]


def bench_layouts(which: tuple[str, ...] = ("stereo", "marker", "features"),
                  seconds: float | None = None) -> list[dict[str, Any]]:
    runs = {"stereo": bench_stereo_layouts, "marker": bench_marker_layouts, "features": bench_features_layouts,
            "priority": bench_stereo_priority}
    lines = []
    for name in which:
        lines += runs[name](seconds) if seconds else runs[name]()
    lines.append(host(bench="layouts"))
    return lines


if __name__ == "__main__":
    parser = argparse.ArgumentParser(prog="python -m tests.bench.layouts")
    parser.add_argument("which", nargs="*", choices=("stereo", "marker", "features", "priority"))
    parser.add_argument("--seconds", type=float)
    args = parser.parse_args()
    for line in bench_layouts(tuple(args.which) or ("stereo", "marker", "features"), args.seconds):
        print(json.dumps(line), flush=True)
