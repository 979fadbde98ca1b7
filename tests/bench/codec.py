"""The codec's own cost per message, warm and cold, in one process.

Each step (build a ``protocol.Image`` around a 640x480 mono8 frame, ``encode`` it, ``decode``
its payload, ``peek`` at it as the recorder does; the same four for a marker ``Pose``) is timed
``CALLS`` times two ways:

* ``warm``: back to back, the figures a micro-benchmark gives;
* ``cold``: each call the first after ``SLEEP_S`` asleep, as in a node fed at 60 fps or the
  transport benchmark's 100 Hz latency phase: the core idles in between, other work runs on
  it, and the call finds its code and data out of the caches.

p50 per step and condition, and cold / warm. The transport and marker benchmarks' typed
overheads are sums of such steps (see docs/benchmarks.md).
``python -m tests.bench codec`` prints the lines (about 20 s).
"""

from __future__ import annotations

import json
import statistics
import time
from collections.abc import Callable
from typing import Any

from protocol import decode, encode, peek
from tests.bench.traffic import ImageCase, pose_message

CALLS = 200
WARMUP = 20
SLEEP_S = 0.016


def timed(step: Callable[[], object], pause_s: float) -> float:
    """p50 in us of ``step`` over ``CALLS`` calls, each after ``pause_s`` asleep (0: back to back)."""
    times = []
    for _ in range(WARMUP + CALLS):
        if pause_s:
            time.sleep(pause_s)
        started = time.perf_counter_ns()
        step()
        times.append(time.perf_counter_ns() - started)
    return statistics.median(times[WARMUP:]) / 1e3


def steps() -> dict[str, Callable[[], object]]:
    """The steps timed, by name: each builds, encodes, decodes or peeks at one message."""
    case = ImageCase((480, 640), "mono8")
    frame = case.frame()
    image, pose = case.message(frame, 0), pose_message(0)
    image_payload, pose_payload = encode(image), encode(pose)
    return {
        "image_build": lambda: case.message(frame, 1), "image_encode": lambda: encode(image),
        "image_decode": lambda: decode(image_payload), "image_peek": lambda: peek(image_payload),
        "pose_build": lambda: pose_message(1), "pose_encode": lambda: encode(pose),
        "pose_decode": lambda: decode(pose_payload), "pose_peek": lambda: peek(pose_payload),
    }


def bench_codec() -> list[dict[str, Any]]:
    lines = []
    for name, step in steps().items():
        warm, cold = timed(step, 0.0), timed(step, SLEEP_S)
        lines.append({"bench": "codec", "step": name, "warm_p50_us": round(warm, 1), "cold_p50_us": round(cold, 1),
                      "cold_over_warm": round(cold / warm, 1), "sleep_s": SLEEP_S, "calls": CALLS})
    return lines


if __name__ == "__main__":
    for line in bench_codec():
        print(json.dumps(line), flush=True)
