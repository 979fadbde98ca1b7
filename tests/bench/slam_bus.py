"""Monocular SLAM over the bus: frame stamp -> pose at a client app, against the same frames in one process.

The synthetic ``room`` at 640x480, its first ``FRAMES`` frames rendered beforehand, published at ``FPS``
(a rate the node keeps up with on this machine; stamps are the wall clock as the frames go out, so
the map's keyframes come ``FPS``-paced in both variants). The node's default options (mapping process,
``depth`` 2), OpenCV's default threads (as the node runs).

* ``in_process_paced``: each frame through ``SlamSystem`` (mapping process) and its pose message built as
  the node does (``slam.node.as_pose``), one every 1/``FPS`` s and stamped then (``tests.bench.markers``
  says why paced). p50 / p99 ms after ``WARMUP`` frames, frames tracked.
* ``pipeline``: ``tests.bench.frame_source`` publishes the frames (mono8 ``Image`` + ``CameraInfo``), an
  ``artrack`` ``slam`` node (its own process) tracks them, and this process follows the pose as a client
  app (``tests.bench.live``; the router runs here too). Latency per frame = arrival of its pose here -
  the frame's stamp (two hops). Beside it the node's ``NodeStats`` (processing, latency stamp -> pose
  published, frames dropped while busy) and the CPU the node used (``node_cores``, 1.0 = one busy core).
* ``overhead``: pipeline p50 - in-process p50.

``python -m tests.bench.slam_bus`` prints the lines (about 80 s).
"""

from __future__ import annotations

import json
import time
from typing import Any

import numpy as np

from protocol import Header, TrackingState
from services.slam.node import as_pose
from services.slam.system import SlamSystem
from services.synthetic import make_scene
from tests.bench.link import at_rate, cpu_seconds
from tests.bench.live import LiveBus

SCENE = "room"
WIDTH, HEIGHT = 640, 480
FPS = 5.0
FRAMES = 150
WARMUP = 10


def _p50_p99(values_ms: list[float]) -> dict[str, float]:
    p50, p99 = np.percentile(values_ms, [50, 99])
    return {"p50_ms": round(float(p50), 2), "p99_ms": round(float(p99), 2)}


def in_process() -> dict[str, Any]:
    """The frames through a system with its mapping process, one every 1/``FPS`` s, as the node gets them."""
    scene = make_scene(SCENE, width=WIDTH, height=HEIGHT)
    camera = scene.cameras[0]
    frames = [scene.render(i).images[camera.name] for i in range(FRAMES)]
    system = SlamSystem(camera)
    times, tracked = [], 0
    try:
        for seq, image in enumerate(at_rate(frames, 1.0 / FPS)):
            started = time.perf_counter()
            header = Header(stamp_ns=time.time_ns(), frame_id="map", seq=seq)
            result = system.process(header.stamp_ns, image)
            as_pose(header, camera.name, result)
            times.append((time.perf_counter() - started) * 1e3)
            tracked += result.state is TrackingState.TRACKING
    finally:
        system.close()
    return {**_p50_p99(times[WARMUP:]), "tracked": tracked}


def pipeline() -> dict[str, Any]:
    """Source -> slam node -> this client at ``FPS``: latency per frame, the node's own figures."""
    with LiveBus("slam_probe") as live:
        (node,) = live.nodes({"slam": ("slam", {"camera": "cam0"})})
        source = live.source(SCENE, FPS, FRAMES, FRAMES, width=WIDTH, height=HEIGHT)
        cpu_before = cpu_seconds(node.pid)
        sent = live.follow(source)
        node_cores = (cpu_seconds(node.pid) - cpu_before) / (FRAMES / sent.get("rate_hz", FPS))
        latencies = live.latencies(WARMUP)
        tracked = sum(update.pose.state is TrackingState.TRACKING for update in live.arrived)
        stats = live.stats(["slam"])["slam"]
    if stats is None:
        raise RuntimeError("the slam node did not answer with its stats")
    frames_in = next((s.messages for s in stats.streams if s.key == live.bus.keys.image("cam0")), 0)
    return {**_p50_p99(latencies), "frames_sent": sent.get("sent"), "source_rate_hz": sent.get("rate_hz"),
            "source_late": sent.get("late"), "frames_received": frames_in, "poses": len(live.arrived),
            "tracked": tracked, "dropped": stats.dropped, "node_p50_ms": stats.processing_ms_p50,
            "node_p99_ms": stats.processing_ms_p99, "node_latency_p50_ms": stats.latency_ms_p50,
            "node_latency_p99_ms": stats.latency_ms_p99, "node_cores": round(node_cores, 2)}


def bench_slam_bus() -> list[dict[str, Any]]:
    local, live = in_process(), pipeline()
    common = {"bench": "slam_bus", "width": WIDTH, "height": HEIGHT, "fps": FPS, "frames": FRAMES}
    return [
        {**common, "variant": "in_process_paced", **local},
        {**common, "variant": "pipeline", "hops": 2, **live},
        {**common, "variant": "overhead", "p50_ms": round(live["p50_ms"] - local["p50_ms"], 2)},
    ]


if __name__ == "__main__":
    for line in bench_slam_bus():
        print(json.dumps(line), flush=True)
