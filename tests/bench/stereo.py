"""Stereo tracking speed: the stages in one process, and the live pipeline at motion-capture rates.

The ``ir_rig`` scene, two 640x480 cameras, ``BODIES`` bodies; the ``stereo`` tracker's settings
(blobs nodes' and rigid_bodies node's defaults).

* ``in_process``: per instant, in this process, back to back over ``INSTANTS`` pre-rendered
  instants: ``blobs`` (the IR detector on every camera's frame, one after the other), then
  ``triangulate_blobs`` and ``match_bodies`` as the node runs them, then ``messages`` (the node's
  Points3D and Pose messages built and encoded). ``triangulation`` is the final points'
  batched DLT + Gauss-Newton + covariance redone alone, and ``correspondence`` what the rest of
  ``triangulate_blobs`` takes (its total minus that); ``fit`` is the chosen bodies' rigid fits
  with covariance redone alone (one batched least squares, then the covariances in one batch, as
  ``match_bodies`` does), ``matching`` the rest of ``match_bodies``. ``total``: blobs +
  triangulate_blobs + match_bodies + messages; ``bodies_full``: the same less the blobs, the node's work
  per instant with ``predict=false``. ``bodies_predicted``: the node's work per instant with prediction
  (its default), on the same blobs, stamped with the scene's time (30 Hz): ``node.BodiesPerSet`` (the
  bodies followed in the images, ``labelled.track_blobs``; the first two instants seed the motions and
  take the full path) and its messages built and encoded, before the full path on odd instants and
  after it on even ones; ``predicted_triangulation`` and ``predicted_fit``: its points' triangulation
  and its bodies' fits redone alone, as ``triangulation`` and ``fit`` are for the full path. p50 / p99
  ms after ``WARMUP`` instants.
  ``in_process_paced``: the same, one instant every 1/rate s, as the pipeline gets them.
* ``pipeline``: ``tests.bench.frame_source`` publishes pre-rendered frame pairs at ``rate``
  (Image + CameraInfo per camera, the capture node's way), a ``blobs`` node per camera and the
  ``rigid_bodies`` node (given the scene's bodies in a bodies file) track, each node its own
  process, and this process follows the poses as a client app (``services.client``). Per
  instant: latency = arrival of its last pose here - the pair's stamp (three hops: source ->
  blobs -> rigid_bodies -> here); ``updates_per_s``: instants whose poses arrived, per second of
  sending; ``dropped_pairs``: instants sent that never became a joined set (the ``points``
  messages counted here); the nodes' own drop counts and processing times (``NodeStats``)
  beside, and the CPU each used while the pairs flowed (``cores``, 1.0 = one busy core; the
  source's own is left out, the bench process's holds the client and the router).
  ``ratio_p50``: pipeline latency p50 over the paced in-process total p50. Target: ``rate``
  >= 240 sustained, no pair dropped, p50 <= 3 ms, p99 <= 5 ms.

``python -m tests.bench.stereo [RATE ...]`` prints the lines (about 30 s per rate, default 120, 240 and 360).
"""

from __future__ import annotations

import json
import shutil
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np

from protocol import encode
from protocol.detections import Blobs
from protocol.message import Header
from services.detection.blobs import node as blobs_node
from services.estimation.bodies import node as rigid_bodies_node
from services.estimation.bodies.correspondence import rig_geometry, triangulate_blobs
from services.estimation.bodies.file import save_bodies
from services.estimation.bodies.labelled import Found
from services.estimation.bodies.rigid import Matching, match_bodies
from services.geometry.absolute_orientation import least_squares_transforms, pose_covariances
from services.geometry.triangulation import triangulate_many
from services.synthetic import make_scene
from tests.bench.figures import host
from tests.bench.link import at_rate, cpu_seconds
from tests.bench.live import LiveBus

ROOT = Path(__file__).resolve().parents[2]
RATES = (120.0, 240.0, 360.0)
SECONDS = 10.0
INSTANTS = 480
BODIES = 3
WARMUP = 20
START_S = 30.0
QUIET_S = 2.0
STAGES = ("blobs", "correspondence", "triangulation", "matching", "fit", "messages", "total", "bodies_full",
          "bodies_predicted", "predicted_triangulation", "predicted_fit")
TARGET = {"rate_hz": 240.0, "p50_ms": 3.0, "p99_ms": 5.0}


def in_process(period_s: float = 0.0) -> dict[str, dict[str, float]]:
    """Per-stage p50 / p99 ms per instant, one instant every ``period_s`` (0: back to back)."""
    scene = make_scene("ir_rig", body_count=BODIES)
    names = [camera.name for camera in scene.cameras]
    instants = [scene.render(i) for i in range(INSTANTS)]
    detect = blobs_node.detector(blobs_node.Params())
    node = rigid_bodies_node.Params(cameras=tuple(names))
    correspondence, matching_options = node.correspondence, node.match
    noise = rigid_bodies_node.PointNoise(correspondence)
    bodies, stack = scene.bodies, rig_geometry(scene.cameras).stack
    followed = rigid_bodies_node.BodiesPerSet(bodies, node)
    times: dict[str, list[float]] = defaultdict(list)
    for index, instant in enumerate(at_rate(instants, period_s)):
        t0 = time.perf_counter()
        found_blobs = [blobs_node.as_message(_header(name), "ir", detect(instant.images[name])) for name in names]
        blobs_s = time.perf_counter() - t0
        stamp_ns = round(scene.time_s(index) * 1e9)
        if index % 2:
            followed_s, labelled = _predicted(followed, stamp_ns, list(scene.cameras), found_blobs, list(bodies))
        t1 = time.perf_counter()
        found = triangulate_blobs(scene.cameras, [rigid_bodies_node.pixels(b, False) for b in found_blobs],
                                  correspondence)
        t2 = time.perf_counter()
        points, covariances = noise.arrays(found)
        matching = match_bodies(bodies, points, covariances, matching_options) if len(found) else Matching()
        t3 = time.perf_counter()
        pose_header = _header("world")
        messages = [rigid_bodies_node.points_message(pose_header, found, list(bodies), matching, covariances),
                    *rigid_bodies_node.body_poses(pose_header, matching)]
        for message in messages:
            encode(message)
        t4 = time.perf_counter()
        if not index % 2:
            followed_s, labelled = _predicted(followed, stamp_ns, list(scene.cameras), found_blobs, list(bodies))
        times["bodies_predicted"].append(followed_s)
        times["predicted_triangulation"].append(_triangulation_alone(stack, labelled.points, found_blobs,
                                                                     correspondence.covariance_sigma_px))
        times["predicted_fit"].append(_fit_alone(bodies, labelled.points_world, labelled.covariances,
                                                 labelled.matching))
        alone_triangulation = _triangulation_alone(stack, found, found_blobs, correspondence.covariance_sigma_px)
        alone_fit = _fit_alone(bodies, points, covariances, matching)
        times["blobs"].append(blobs_s)
        times["correspondence"].append(t2 - t1 - alone_triangulation)
        times["triangulation"].append(alone_triangulation)
        times["matching"].append(t3 - t2 - alone_fit)
        times["fit"].append(alone_fit)
        times["messages"].append(t4 - t3)
        times["total"].append(blobs_s + t4 - t1)
        times["bodies_full"].append(t4 - t1)
    return {stage: _percentiles(times[stage]) for stage in STAGES}


def _predicted(followed: rigid_bodies_node.BodiesPerSet, stamp_ns: int, cameras: list, blobs: list[Blobs],
               names: list[str]) -> tuple[float, Found]:
    """Seconds the node's work on one instant takes with prediction (``BodiesPerSet`` on the ``blobs`` messages
    and its messages), and what it found."""
    started = time.perf_counter()
    found, predicted = followed(stamp_ns, cameras, [rigid_bodies_node.pixels(b, False) for b in blobs],
                                [rigid_bodies_node.split_parts(b) for b in blobs])
    header = _header("world")
    messages = [rigid_bodies_node.points_message(header, found.points, names, found.matching, found.covariances),
                *rigid_bodies_node.body_poses(header, found.matching),
                *rigid_bodies_node.predicted_poses(header, predicted)]
    for message in messages:
        encode(message)
    return time.perf_counter() - started, found


def _header(frame_id: str) -> Header:
    return Header(stamp_ns=time.time_ns(), frame_id=frame_id, seq=0)


def _triangulation_alone(stack: Any, found: list, blobs: list, sigma_px: float) -> float:
    """Seconds the found points' triangulation takes alone (their views, batched as the node does)."""
    pixels = np.zeros((len(found), len(stack), 2))
    seen = np.zeros((len(found), len(stack)), bool)
    for row, point in enumerate(found):
        for c, i in zip(point.camera_indices, point.blob_indices, strict=True):
            pixels[row, c], seen[row, c] = _observed(blobs[c])[i], True
    started = time.perf_counter()
    triangulate_many(stack, pixels, seen, sigma_px)
    return time.perf_counter() - started


def _observed(blobs: Blobs) -> np.ndarray:
    """(N + 2 P, 2) px: the blobs a point's views index, the clean ones then the split blobs' parts."""
    return np.concatenate([rigid_bodies_node.pixels(blobs, False), rigid_bodies_node.split_parts(blobs).reshape(-1, 2)])


def _fit_alone(bodies: dict[str, np.ndarray], points: np.ndarray, covariances: np.ndarray, matching: Matching) -> float:
    """Seconds the chosen bodies' rigid fits take alone, done as ``match_bodies`` does them: one batched
    least squares (``least_squares_transforms``), then their covariances in one batch (``pose_covariances``)."""
    chosen = list(matching.bodies.items())
    if not chosen:
        return 0.0
    widest = max(len(bodies[name]) for name, _ in chosen)
    spheres, world = np.zeros((len(chosen), widest, 3)), np.zeros((len(chosen), widest, 3))
    sigma = np.zeros((len(chosen), widest, 3, 3))
    used = np.zeros((len(chosen), widest), bool)
    for row, (name, match) in enumerate(chosen):
        count = len(bodies[name])
        spheres[row, :count], used[row, :count] = bodies[name], match.indices >= 0
        world[row, :count] = points[np.maximum(match.indices, 0)]
        sigma[row, :count] = covariances[np.maximum(match.indices, 0)]
    started = time.perf_counter()
    transforms, _ = least_squares_transforms(spheres, world, used)
    pose_covariances(transforms, spheres, sigma, used)
    return time.perf_counter() - started


def _percentiles(seconds: list[float]) -> dict[str, float]:
    p50, p99 = np.percentile(np.array(seconds[WARMUP:]) * 1e3, [50, 99])
    return {"p50_ms": round(float(p50), 3), "p99_ms": round(float(p99), 3)}


def pipeline(rate: float) -> dict[str, Any]:
    """Source -> blobs nodes -> rigid_bodies node -> this client at ``rate`` Hz for ``SECONDS``."""
    frames = int(rate * SECONDS)
    names = [f"cam{i}" for i in range(2)]
    bodies_file = Path(tempfile.mkdtemp(prefix="stereo_bench")) / "bodies.yaml"
    save_bodies(bodies_file, make_scene("ir_rig", body_count=BODIES).bodies)
    points_seen: list[int] = []
    try:
        with LiveBus("stereo_probe") as live:
            points_subscriber = live.session.declare_subscriber(live.bus.keys.points(),
                                                                lambda sample: points_seen.append(1))
            nodes = {f"blobs-{name}": ("blobs", {"camera": name}) for name in names}
            nodes["bodies"] = ("rigid_bodies", {"cameras": names, "bodies": str(bodies_file)})
            node_processes = live.nodes(nodes)
            source = live.source("ir_rig", rate, frames)
            cpu_before = [cpu_seconds(p.pid) for p in node_processes]
            own_before = time.process_time()
            sent = live.follow(source)
            seconds = frames / sent.get("rate_hz", rate)
            cores = {name: round((cpu_seconds(p.pid) - before) / seconds, 2)
                     for name, p, before in zip(nodes, node_processes, cpu_before, strict=True)}
            cores["client_and_router"] = round((time.process_time() - own_before) / seconds, 2)
            points_subscriber.undeclare()
            latencies = live.latencies(WARMUP)
            seqs = {update.pose.header.seq for update in live.arrived}
            stats = live.stats(list(nodes))
            poses = len(live.arrived)
    finally:
        shutil.rmtree(bodies_file.parent, ignore_errors=True)
    p50, p99 = np.percentile(latencies, [50, 99])
    return {"rate_hz": rate, "sent": sent.get("sent"), "source_rate_hz": sent.get("rate_hz"),
            "source_late": sent.get("late"), "p50_ms": round(float(p50), 3), "p99_ms": round(float(p99), 3),
            "updates_per_s": round(len(seqs) * sent.get("rate_hz", rate) / frames, 1),
            "instants_with_poses": len(seqs), "poses": poses,
            "dropped_pairs": frames - len(points_seen),
            "node_dropped": {name: s.dropped if s else None for name, s in stats.items()},
            "node_p50_ms": {name: s.processing_ms_p50 if s else None for name, s in stats.items()},
            "node_p99_ms": {name: s.processing_ms_p99 if s else None for name, s in stats.items()},
            "cores": cores}


def bench_stereo(rates: tuple[float, ...] = RATES) -> list[dict[str, Any]]:
    common = {"bench": "stereo_tracking", "cameras": 2, "width": 640, "height": 480, "bodies": BODIES}
    lines = [{**common, "variant": "in_process", "stages": in_process()}]
    for rate in rates:
        paced = in_process(1.0 / rate)
        live = pipeline(rate)
        met = (live["dropped_pairs"] == 0 and live["updates_per_s"] >= TARGET["rate_hz"] * 0.99
               and live["p50_ms"] <= TARGET["p50_ms"] and live["p99_ms"] <= TARGET["p99_ms"])
        lines += [{**common, "variant": "in_process_paced", "rate_hz": rate, "stages": paced},
                  {**common, "variant": "pipeline", "hops": 3, **live,
                   "ratio_p50": round(live["p50_ms"] / paced["total"]["p50_ms"], 2), "target": TARGET, "met": met}]
    lines.append(host(**common))
    return lines


if __name__ == "__main__":
    for line in bench_stereo(tuple(float(a) for a in sys.argv[1:]) or RATES):
        print(json.dumps(line), flush=True)
    sys.exit(0)
