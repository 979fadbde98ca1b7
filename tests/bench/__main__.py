"""``python -m tests.bench``: run every benchmark, print one JSON line per figure, then the machine.

Images: for each size, ``RUNS`` rounds; each round measures typed and raw back to back,
the order alternating from round to round (typed first, raw first, ...). Both variants use
the same QoS: the FRAME role's for the latency phase (what images use), the RESULT role's
for the flood (its ``CongestionControl.BLOCK`` makes the count of received messages a
zero-loss throughput). Poses: ``RUNS`` runs with the RESULT role's QoS in both phases.
Both processes fix glibc's malloc thresholds first (see ``tests.bench.memory``).
Then the scene renderers, the recorder and replay, the viewer, marker tracking (the live
pipeline against the same work in one process) and the marker estimators' accuracy against
ground truth (each module's docstring says what it measures). Progress goes to stderr.
"""

from __future__ import annotations

import json
import os
import sys
from typing import Any

from protocol import encode
from services.runtime.memory import tune_malloc
from services.runtime.pubsub import Role
from tests.accuracy.report import report_lines
from tests.bench.figures import comparison_lines, machine_line, variant_line
from tests.bench.link import Sink
from tests.bench.markers import bench_markers
from tests.bench.recorder import bench_recorder
from tests.bench.runs import Run, measure
from tests.bench.scenes import bench_scenes
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
    for round_ in range(RUNS):
        for name in list(variants)[:: 1 if round_ % 2 == 0 else -1]:
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


def main() -> None:
    malloc = tune_malloc()
    load_before = os.getloadavg()[0]
    with Sink() as sink:
        for case in IMAGE_CASES:
            emit(image_bench(sink, case))
        emit(pose_bench(sink))
    for name, bench in (("scenes", bench_scenes), ("recorder", bench_recorder), ("viewer", bench_viewer),
                        ("markers", bench_markers), ("marker accuracy", report_lines)):
        progress(name)
        emit(bench())
    emit([machine_line(malloc, load_before)])


def emit(lines: list[dict[str, Any]]) -> None:
    for line in lines:
        print(json.dumps(line), flush=True)


if __name__ == "__main__":
    main()
