"""Marker tracking speed: the live pipeline against the same work done in one process.

* ``in_process``: the synthetic ``markers`` scene's frames (640x480, ``FRAMES`` of them) are
  rendered first; then each is detected (the corners refined with the calibration, as the node does once it
  has one) and its markers' poses estimated in this process, with the pipeline's own settings, back to back.
  Per-frame time p50/p99.
* ``in_process_paced``: the same, one frame every 1/``FPS`` s as the live pipeline gets
  them. Idle gaps between frames cost the work itself cache and clock warmth, so this is the
  fair baseline for a paced pipeline; both are reported.
* ``pipeline``: a capture node sends the scene's frames at ``FPS`` (its first ``PRERENDER`` instants,
  rendered before the run and cycled) and publishes them; a marker
  node detects and estimates; this process subscribes to the poses. The two nodes run in one
  process as the ``marker`` tracker runs them (the frame passed by reference: one process hop,
  marker node -> here); ``pipeline_apart`` runs each in its own process (two hops: capture ->
  marker node -> here). Per frame, latency = arrival here of the frame's last pose - the frame's
  capture stamp. Frames are counted in and out: the node's
  ``dropped`` (frames replaced before they were processed) and the frames whose poses arrived.
  The node's own ``NodeStats`` give its processing time and its latency (each frame's age when
  the node was done with it: capture stamp -> its poses and detections published).
  The processes meet through an in-process router on a free loopback port. ``tests.bench.apps``
  runs the same pipeline with client apps subscribed beside this process.
* ``in_process_subpix``: as ``in_process`` with OpenCV's ``subpix`` corner refinement instead of
  the default ``lines`` (which runs ``subpix`` and then fits lines to the sides): what the
  default refinement costs.
* ``pipeline_overhead``, ``pipeline_apart_overhead``: pipeline p50 - in-process p50, against both
  baselines. Target: <= 0.5 ms over the paced baseline, and ``FPS`` sustained with no frame
  dropped. The paced loop is the one judged because it gets the frames as the pipeline does,
  one every 1/``FPS`` s; such a gap costs every code path a cold start (``tests.bench.codec``
  measures one: a pose decoded back to back and as the first call after a sleep), which
  back-to-back work never pays.

``python -m tests.bench.markers`` prints the lines (about 20 s).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
import uuid
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np
import zenoh

from protocol.system import NodeStats
from services.bus.discovery import client_states, node_states
from services.bus.pubsub import Listener
from services.bus.session import BusConfig, open_session
from services.client import PoseUpdate, connect
from services.detection.markers.settings import DetectorSettings
from services.estimation.markers.pose import MarkerPoseEstimator
from services.launcher.observe import wait_for_nodes
from services.launcher.pipeline import GroupMember, group_command, node_command
from services.launcher.router import router_config
from services.runtime.flow import FlowPlan
from services.synthetic import make_scene
from tests.bench.link import at_rate, cpu_seconds, free_port, stop_processes

ROOT = Path(__file__).resolve().parents[2]
APP = ROOT / "examples" / "track_marker.py"
FPS = 60.0
FRAMES = 600
MARKER_LENGTH = 0.05
START_S = 30.0
QUIET_S = 2.0
WARMUP = 10
PROBE = "latency_probe"
OVERHEAD_TARGET_MS = 0.5
PRERENDER = 240
"""Instants the capture renders before the run and cycles: the source costs what a camera does, and in a
group its rendering does not share the interpreter with the tracker's thread while the frames flow."""


def in_process(settings: DetectorSettings, period_s: float = 0.0) -> dict[str, float]:
    """Detect + estimate per frame of the scene, in this process, one frame per ``period_s``
    (0: back to back): p50 / p99 ms of the work alone."""
    scene = make_scene("markers")
    camera = scene.cameras[0]
    frames = [scene.render(i).images[camera.name] for i in range(FRAMES)]
    detector, estimator = settings.detector(), MarkerPoseEstimator()
    times = []
    for image in at_rate(frames, period_s):
        started = time.perf_counter()
        found = detector.detect(image, camera.K, camera.dist)
        estimator.estimate(found.ids, found.corners, found.side_m, camera.K, camera.dist)
        times.append((time.perf_counter() - started) * 1e3)
    p50, p99 = np.percentile(times[WARMUP:], [50, 99])
    return {"p50_ms": round(float(p50), 3), "p99_ms": round(float(p99), 3)}


def pipeline(settings: DetectorSettings, apps: int = 0, grouped: bool = True, **node: Any) -> dict[str, Any]:
    """The capture -> marker node -> here pipeline at FPS: latency per frame and frames lost.

    ``grouped`` (the ``marker`` tracker's way): the capture and the marker node in one process, the frame
    passed by reference; else each in a process of its own, the frame crossing between them.

    With ``apps`` > 0, that many ``examples/track_marker.py`` processes follow every pose of the
    rig meanwhile (subscribed before the first frame); ``app_poses_min`` is the fewest poses one
    of them had at the end, against ``poses``, the count that reached this process, and
    ``apps_cores`` the CPU they used together while the frames flowed (cores, 1.0 = one busy core).
    """
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = zenoh.open(router_config((endpoint,), (), None))
    bus = BusConfig(connect=(endpoint,), rig=f"bench{uuid.uuid4().hex[:6]}", autostart_router=False)
    env = {**os.environ, **bus.to_env()}
    session = open_session(bus)
    probe = connect(connect=endpoint, namespace=bus.namespace, rig=bus.rig, app=PROBE)
    arrived: list[PoseUpdate] = []
    probe.on_pose("**", arrived.append)
    final: dict[str, NodeStats] = {}
    last_stats = Listener(session, bus.keys.stats("marker"), NodeStats,
                          lambda received: final.__setitem__("marker", received.message))
    processes: list[subprocess.Popen] = []
    try:
        processes += [subprocess.Popen([sys.executable, str(APP)], cwd=ROOT, env=env, stdout=subprocess.DEVNULL)
                      for _ in range(apps)]
        marker = {"camera": "cam0", **settings.model_dump(exclude_defaults=True), **node}
        capture_params = {"source": ["synthetic:markers"], "fps": FPS, "frames": FRAMES, "wait_for_subscriber": True,
                          "prerender": PRERENDER}
        wait_for_apps(session, bus, apps)
        if grouped:
            members = [GroupMember(name="marker", kind="marker_pose", params=marker,
                                   flow=FlowPlan(upstream=("capture",))),
                       GroupMember(name="capture", kind="capture", params=capture_params, source=True)]
            capture = subprocess.Popen(group_command("tracker", members), cwd=ROOT, env=env)
        else:
            processes.append(subprocess.Popen(node_command("marker_pose", "marker", marker), cwd=ROOT, env=env))
            if wait_for_nodes(session, bus.keys, {"marker"}, START_S) != {"marker"}:
                raise RuntimeError("the marker node did not come up")
            capture = subprocess.Popen(node_command("capture", "capture", capture_params), cwd=ROOT, env=env)
        processes.append(capture)
        started, apps_cpu = time.monotonic(), sum(cpu_seconds(p.pid) for p in processes[:apps])
        quiet_since, seen = started, 0
        while time.monotonic() - quiet_since < QUIET_S or capture.poll() is None:
            time.sleep(0.1)
            if len(arrived) != seen:
                quiet_since, seen = time.monotonic(), len(arrived)
        arrivals: dict[int, list[int]] = defaultdict(list)
        stamps: dict[int, int] = {}
        for update in arrived:
            arrivals[update.pose.header.seq].append(update.received_ns)
            stamps[update.pose.header.seq] = update.pose.header.stamp_ns
        apps_cores = (sum(cpu_seconds(p.pid) for p in processes[:apps]) - apps_cpu) / (time.monotonic() - started)
        stats = final.get("marker") if grouped else node_states(session, bus.keys, 2.0).get((bus.rig, "marker"))
        images = next((s.messages for s in stats.streams if s.key == bus.keys.image("cam0")), 0) if stats else 0
        latencies = [(max(arrivals[seq]) - stamps[seq]) / 1e6 for seq in sorted(arrivals)][WARMUP:]
        p50, p99 = np.percentile(latencies, [50, 99])
        return {"p50_ms": round(float(p50), 3), "p99_ms": round(float(p99), 3), "frames_sent": FRAMES,
                "frames_with_poses": len(arrivals), "frames_received": images,
                "dropped": stats.dropped if stats else None,
                "node_p50_ms": stats.processing_ms_p50 if stats else None,
                "node_p99_ms": stats.processing_ms_p99 if stats else None,
                "node_latency_p50_ms": stats.latency_ms_p50 if stats else None,
                "node_latency_p99_ms": stats.latency_ms_p99 if stats else None,
                **({"apps": apps, "poses": sum(map(len, arrivals.values())),
                    "app_poses_min": min(app_poses(session, bus), default=0),
                    "apps_cores": round(apps_cores, 3)} if apps else {})}
    finally:
        last_stats.close()
        probe.close()
        stop_processes(processes)
        session.close()
        router.close()


def app_poses(session: zenoh.Session, bus: BusConfig) -> list[int]:
    """Poses received so far by each client app of the rig that answers (all its subscriptions)."""
    return [sum(s.received for s in state.subscriptions)
            for (rig, _), state in client_states(session, bus.keys, 1.0).items()
            if rig == bus.rig and state.app != PROBE]


def wait_for_apps(session: zenoh.Session, bus: BusConfig, count: int) -> None:
    """Return once ``count`` client apps of the rig answer with a subscription; RuntimeError after ``START_S``."""
    deadline = time.monotonic() + START_S
    while count and (ready := sum(1 for (rig, _), state in client_states(session, bus.keys, 0.5).items()
                        if rig == bus.rig and state.app != PROBE and state.subscriptions)) < count:
        if time.monotonic() > deadline:
            raise RuntimeError(f"{ready} of {count} client apps subscribed within {START_S:.0f} s")


def bench_markers() -> list[dict[str, Any]]:
    settings = DetectorSettings(marker_length=MARKER_LENGTH)
    local, paced = in_process(settings), in_process(settings, 1.0 / FPS)
    live, apart = pipeline(settings), pipeline(settings, grouped=False)
    subpix = in_process(settings.model_copy(update={"refinement": "subpix"}))
    common = {"bench": "marker_tracking", "width": 640, "height": 480, "fps": FPS, "frames": FRAMES}
    lines = [{**common, "variant": "in_process", **local}, {**common, "variant": "in_process_paced", **paced},
             {**common, "variant": "in_process_subpix", **subpix}]
    for name, run, hops in (("pipeline", live, 1), ("pipeline_apart", apart, 2)):
        over, over_paced = run["p50_ms"] - local["p50_ms"], run["p50_ms"] - paced["p50_ms"]
        lines += [{**common, "variant": name, "hops": hops, **run},
                  {**common, "variant": f"{name}_overhead", "p50_ms": round(over, 3),
                   "p50_ms_vs_paced": round(over_paced, 3), "target_ms": OVERHEAD_TARGET_MS,
                   "met": over_paced <= OVERHEAD_TARGET_MS,
                   "no_frame_dropped": run["dropped"] == 0 and run["frames_received"] == FRAMES}]
    return lines


if __name__ == "__main__":
    for line in bench_markers():
        print(json.dumps(line), flush=True)
    sys.exit(0)
