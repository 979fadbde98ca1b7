"""Image-target tracking over the bus: frame stamp -> pose at a client app, against the same frames in one
process.

The ``planar_target`` scene at 640x480, its first ``FRAMES`` frames rendered beforehand; its own target
(``synthetic:planar_target``, in a library of its own as ``artrack run`` writes it), the features node's
default options, OpenCV's default threads (as the node runs).

* ``in_process``: each frame tracked in this process as the node tracks it (``features_node``'s
  trackers through ``track_targets``, the pose message built), back to back; ``in_process_paced``:
  the same, one frame every 1/``FPS`` s as the pipeline gets them (``tests.bench.markers`` says why
  both). p50 / p99 ms after ``WARMUP`` frames.
* ``pipeline``: ``tests.bench.frame_source`` publishes the same frames at ``FPS`` (mono8 ``Image`` +
  ``CameraInfo``, the capture node's way), a ``features`` node (its own process) tracks them, and
  this process follows the pose as a client app (``tests.bench.live``; the router runs in this
  process too). Per frame: latency = arrival of its pose here - the frame's stamp (two hops:
  source -> node -> here). Beside it the node's ``NodeStats``: processing time per frame, latency
  (stamp -> pose published), frames dropped while busy; and the CPU the node used while the frames
  flowed (``node_cores``, 1.0 = one busy core).
* ``where``: the pipeline's p50 split at the node's p50s: ``to_node_ms`` = node latency -
  node processing (publishing, the hop in, waiting in the node's queue, the frame's decode),
  ``node_ms`` = node processing (tracking, the pose message, its publishing), ``to_client_ms`` =
  pipeline - node latency (the pose's hop out through the router); and measured alone here, p50 of
  ``CODEC_RUNS``: ``image_decode_ms`` (one frame's payload decoded) and ``pose_encode_ms``.
* ``overhead``: pipeline p50 - in-process p50, against both. Target: <= ``TARGET_MS`` over the
  paced one.

``python -m tests.bench.features_bus`` prints the lines (about 50 s).
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from functools import cache
from typing import Any

import numpy as np

from protocol import Header, Image, TrackingState, decode, encode
from services.estimation.targets.node import Params, as_pose, load_targets, make_trackers
from services.estimation.targets.tracking import track_targets
from services.launcher.fixtures import scene_target_library
from services.synthetic import make_scene
from tests.bench.link import at_rate, cpu_seconds
from tests.bench.live import LiveBus

SCENE = "planar_target"
TARGET = f"synthetic:{SCENE}"
WIDTH, HEIGHT = 640, 480
FPS = 30.0
FRAMES = 300
WARMUP = 10
CODEC_RUNS = 200
TARGET_MS = 1.5


@cache
def _target() -> dict[str, Any]:
    """The features node's ``target`` and ``targets`` for the scene's own target."""
    found = scene_target_library([TARGET], library_given=False)
    assert found is not None
    return found


def _frames(count: int = FRAMES) -> tuple[list[np.ndarray], Any]:
    """The scene's first ``count`` frames and its camera."""
    scene = make_scene(SCENE, width=WIDTH, height=HEIGHT)
    camera = scene.cameras[0]
    return [scene.render(i).images[camera.name] for i in range(count)], camera


def _p50_p99(values_ms: list[float]) -> dict[str, float]:
    p50, p99 = np.percentile(values_ms, [50, 99])
    return {"p50_ms": round(float(p50), 3), "p99_ms": round(float(p99), 3)}


def in_process(period_s: float = 0.0) -> dict[str, Any]:
    """Each frame tracked as the node does, one every ``period_s`` (0: back to back)."""
    frames, camera = _frames()
    params = Params(**_target())
    trackers = make_trackers(params, load_targets(params))
    times, posed = [], 0
    for seq, image in enumerate(at_rate(frames, period_s)):
        started = time.perf_counter()
        header = Header(stamp_ns=time.time_ns(), frame_id=camera.name, seq=seq)
        poses = [as_pose(header, found) for found in track_targets(trackers, image, camera.K, camera.dist,
                                                                    header.stamp_ns)]
        times.append((time.perf_counter() - started) * 1e3)
        posed += poses[0].state is not TrackingState.LOST
    return {**_p50_p99(times[WARMUP:]), "posed": posed}


def pipeline() -> dict[str, Any]:
    """Source -> features node -> this client at ``FPS``: latency per frame, the node's own figures."""
    with LiveBus("features_probe") as live:
        (node,) = live.nodes({"features": ("features", {"camera": "cam0", **_target()})})
        source = live.source(SCENE, FPS, FRAMES, FRAMES, width=WIDTH, height=HEIGHT)
        cpu_before = cpu_seconds(node.pid)
        sent = live.follow(source)
        node_cores = (cpu_seconds(node.pid) - cpu_before) / (FRAMES / sent.get("rate_hz", FPS))
        latencies = live.latencies(WARMUP)
        posed = sum(update.pose.state is not TrackingState.LOST for update in live.arrived)
        stats = live.stats(["features"])["features"]
    if stats is None:
        raise RuntimeError("the features node did not answer with its stats")
    frames_in = next((s.messages for s in stats.streams if s.key == live.bus.keys.image("cam0")), 0)
    return {**_p50_p99(latencies), "frames_sent": sent.get("sent"), "source_rate_hz": sent.get("rate_hz"),
            "source_late": sent.get("late"), "frames_received": frames_in, "frames_with_poses": len(latencies) + WARMUP,
            "posed": posed, "dropped": stats.dropped, "node_p50_ms": stats.processing_ms_p50,
            "node_p99_ms": stats.processing_ms_p99, "node_latency_p50_ms": stats.latency_ms_p50,
            "node_latency_p99_ms": stats.latency_ms_p99, "node_cores": round(node_cores, 2)}


def _codec_ms(run: Callable[[], object]) -> float:
    times = []
    for _ in range(CODEC_RUNS):
        started = time.perf_counter()
        run()
        times.append((time.perf_counter() - started) * 1e3)
    return round(float(np.percentile(times, 50)), 3)


def codec() -> dict[str, float]:
    """p50 ms of one frame's payload decoded and of one tracked pose encoded, alone in this process."""
    frames, camera = _frames(1)
    header = Header(stamp_ns=time.time_ns(), frame_id=camera.name, seq=0)
    payload = encode(Image(header=header, encoding="mono8", data=frames[0]))
    params = Params(**_target())
    pose = as_pose(header, track_targets(make_trackers(params, load_targets(params)), frames[0], camera.K,
                                         camera.dist, header.stamp_ns)[0])
    return {"image_decode_ms": _codec_ms(lambda: decode(payload)), "pose_encode_ms": _codec_ms(lambda: encode(pose))}


def bench_features_bus() -> list[dict[str, Any]]:
    local, paced, live, costs = in_process(), in_process(1.0 / FPS), pipeline(), codec()
    common = {"bench": "features_bus", "width": WIDTH, "height": HEIGHT, "fps": FPS, "frames": FRAMES}
    node_latency, node_processing = live["node_latency_p50_ms"], live["node_p50_ms"]
    over, over_paced = live["p50_ms"] - local["p50_ms"], live["p50_ms"] - paced["p50_ms"]
    where = {"to_node_ms": round(node_latency - node_processing, 3), "node_ms": round(node_processing, 3),
             "to_client_ms": round(live["p50_ms"] - node_latency, 3), **costs}
    return [
        {**common, "variant": "in_process", **local},
        {**common, "variant": "in_process_paced", **paced},
        {**common, "variant": "pipeline", "hops": 2, **live},
        {**common, "variant": "where", **where},
        {**common, "variant": "overhead", "p50_ms": round(over, 3), "p50_ms_vs_paced": round(over_paced, 3),
         "target_ms": TARGET_MS, "met": over_paced <= TARGET_MS},
    ]


if __name__ == "__main__":
    for line in bench_features_bus():
        print(json.dumps(line), flush=True)
