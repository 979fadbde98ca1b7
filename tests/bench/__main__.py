"""``python -m tests.bench [NAME ...]``: run the benchmarks named (all when none is), print one JSON
line per figure, then the machine. Names, in running order: ``transport``, ``codec``,
``routing``, ``scenes``, ``recorder``, ``viewer``, ``markers``, ``apps``, ``accuracy``, ``blobs``,
``keypoints``, ``features``, ``features_bus``, ``stereo``, ``slam``, ``slam_tracking``, ``slam_bus``,
``slam_realtime``, ``refusals``, ``stops``, ``lossless``, ``layouts``, ``pacing``.

Images: for each size, ``RUNS`` rounds; each round measures typed and raw back to back,
the order alternating from round to round (typed first, raw first, ...). Both variants use
the same QoS: the FRAME role's for the latency phase (what images use), the RESULT role's
for the flood (its ``CongestionControl.BLOCK`` makes the count of received messages a
zero-loss throughput). Poses: ``RUNS`` runs with the RESULT role's QoS in both phases.
Both processes fix glibc's malloc thresholds first (see ``tests.bench.memory``).
Then the codec's steps warm and cold in one process (``codec``), poses through a router
against peer to peer (``routing``), the scene renderers, the recorder and replay, the
viewer, marker tracking (the live pipeline against the same work in one process), the
pipeline with client apps subscribed against none (``apps``), the marker estimators'
accuracy against ground truth, blob detection per frame (``blobs``), keypoint detection per frame
(``keypoints``), image-target recognition and tracking per frame on one core against OpenCV's
per-frame recipes, SIFT and ORB, speed and accuracy (``features``), the same frames' poses over the
bus against in process (``features_bus``) and stereo tracking's stages
in one process against the live pipeline at motion-capture rates (``stereo``), SLAM's bundle
adjustment and pose refinement on synthetic problems (``slam``), SLAM's tracking per frame and local
mapping per keyframe on one core, mapping in a process, on a thread and inline (``slam_tracking``), and the SLAM
node's poses over the bus against in process (``slam_bus``), the SLAM tracker's real-time runs on the room at
30 fps and KITTI at 10 fps, ten each idle and under load, counting frames dropped (``slam_realtime``),
how long ``artrack`` takes to refuse a command that cannot work (``refusals``) and a node or ``artrack up``
to stop on SIGTERM (``stops``), and each tracker's lossless runs idle and under load against its node's work
in one process, with the credits' cost (``lossless``), and the trackers run as ``artrack run`` runs them
with their nodes grouped into processes three ways (``layouts``), and how late a paced source's waits end,
with the kernel's default timer slack and with 1 ns (``pacing``) (each module's docstring says what it
measures).
Progress goes to stderr.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections.abc import Callable
from typing import Any

from protocol import encode
from services.bus.pubsub import Role
from services.runtime.memory import tune_malloc
from tests.accuracy.report import report_lines
from tests.bench.apps import bench_apps
from tests.bench.blobs import bench_blobs
from tests.bench.codec import bench_codec
from tests.bench.features import bench_features
from tests.bench.features_bus import bench_features_bus
from tests.bench.figures import alternating, comparison_lines, machine_line, variant_line
from tests.bench.keypoints import bench_keypoints
from tests.bench.layouts import bench_layouts
from tests.bench.link import Sink
from tests.bench.lossless import bench_lossless
from tests.bench.markers import bench_markers
from tests.bench.pacing import bench_pacing
from tests.bench.recorder import bench_recorder
from tests.bench.refusals import bench_refusals
from tests.bench.routing import bench_routing
from tests.bench.runs import Run, measure
from tests.bench.scenes import bench_scenes
from tests.bench.slam import bench_slam
from tests.bench.slam_bus import bench_slam_bus
from tests.bench.slam_realtime import bench_slam_realtime
from tests.bench.slam_tracking import bench_slam_tracking
from tests.bench.stereo import bench_stereo
from tests.bench.stops import bench_stops
from tests.bench.traffic import (
    ImageCase,
    PoseSender,
    RawImageSender,
    TypedImageSender,
    pose_message,
    raw_reader_spec,
    typed_reader_spec,
)
from tests.bench.viewer import bench_viewer

RUNS = 5
IMAGE_CASES = (ImageCase((480, 640), "mono8"), ImageCase((720, 1280, 3), "bgr8"))


def image_bench(sink: Sink, case: ImageCase) -> list[dict[str, Any]]:
    """Typed and raw images of one size, alternated; their figures and comparisons."""
    frame = case.frame()
    size = case.typed_payload_bytes(frame)
    variants = {
        "typed": (typed_reader_spec(), lambda s, k, role: TypedImageSender(s, k, role, case, frame)),
        "raw": (raw_reader_spec(case.shape, size), lambda s, k, role: RawImageSender(s, k, role, frame, size)),
    }
    runs: dict[str, list[Run]] = {name: [] for name in variants}
    for round_, name in alternating(list(variants), RUNS):
        progress(f"{case.name} {name} {round_ + 1}/{RUNS}")
        reader, make_sender = variants[name]
        runs[name].append(measure(sink, f"bench/{case.name}/{name}/{round_}", reader, make_sender,
                                  Role.FRAME, Role.RESULT))
    lines = [variant_line(case.name, name, size, runs[name]) for name in variants]
    return lines + comparison_lines(case.name, runs["typed"], runs["raw"])


def pose_bench(sink: Sink) -> list[dict[str, Any]]:
    """Typed poses (JSON codec) with the RESULT role's QoS."""
    runs = []
    for round_ in range(RUNS):
        progress(f"pose typed {round_ + 1}/{RUNS}")
        runs.append(measure(sink, f"bench/pose/{round_}", typed_reader_spec(), PoseSender,
                            Role.RESULT, Role.RESULT))
    return [variant_line("pose_json", "typed", len(encode(pose_message(0))), runs)]


def progress(text: str) -> None:
    print(f"bench: {text}", file=sys.stderr, flush=True)


def transport_bench() -> list[dict[str, Any]]:
    """Typed against raw images of each size, then typed poses, over one sink."""
    lines = []
    with Sink() as sink:
        for case in IMAGE_CASES:
            lines += image_bench(sink, case)
        lines += pose_bench(sink)
    return lines


BENCHES: dict[str, Callable[[], list[dict[str, Any]]]] = {
    "transport": transport_bench, "codec": bench_codec, "routing": bench_routing, "scenes": bench_scenes,
    "recorder": bench_recorder, "viewer": bench_viewer, "markers": bench_markers, "apps": bench_apps,
    "accuracy": report_lines, "blobs": bench_blobs, "keypoints": bench_keypoints, "features": bench_features,
    "features_bus": bench_features_bus, "stereo": bench_stereo, "slam": bench_slam,
    "slam_tracking": bench_slam_tracking, "slam_bus": bench_slam_bus, "slam_realtime": bench_slam_realtime,
    "refusals": bench_refusals, "stops": bench_stops, "lossless": bench_lossless, "layouts": bench_layouts,
    "pacing": bench_pacing,
}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m tests.bench", description="artrack's benchmarks (JSON lines)")
    parser.add_argument("names", nargs="*", metavar="NAME",
                        help=f"benchmarks to run, in this order: {', '.join(BENCHES)} (default: all)")
    chosen = set(parser.parse_args(argv).names) or set(BENCHES)
    if unknown := chosen - set(BENCHES):
        parser.error(f"no benchmark named {', '.join(sorted(unknown))} (choose from {', '.join(BENCHES)})")
    malloc = tune_malloc()
    load_before = os.getloadavg()[0]
    for name, bench in BENCHES.items():
        if name in chosen:
            progress(name)
            emit(bench())
    emit([machine_line(malloc, load_before)])


def emit(lines: list[dict[str, Any]]) -> None:
    for line in lines:
        print(json.dumps(line), flush=True)


if __name__ == "__main__":
    main()
