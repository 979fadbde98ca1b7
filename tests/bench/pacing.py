"""How late a paced source's frames go out: ``bench_pacing()`` -> one JSON-able dict per figure.

A thread waits for ``FRAMES`` due times ``1 / rate`` apart, two ways, alternated over ``ROUNDS`` rounds
(``plain`` first in even rounds, ``sharp`` first in odd ones), each on a new thread: ``plain``, a sleep on an
event until the due time (``threading.Event.wait``) with the kernel's default timer slack, and ``sharp``,
``services.runtime.pacing.wait_until`` (the same sleep, the thread's timer slack 1 ns). Figures per way, rate
and condition (``idle``, or ``busy``: a process spinning on each core, ``tests.load.busy``): how late the
waits returned (p50 / p90 / p99 us over the rounds' waits) and the waiting thread's CPU as a share of one
core. ``python -m tests.bench.pacing`` prints the lines.
"""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from services.runtime.pacing import wait_until
from tests.load import busy

RATES = (60.0, 240.0)
FRAMES = 480
ROUNDS = 3


def plain(due: float, stop: threading.Event) -> bool:
    """A sleep on ``stop`` until ``due``."""
    left = due - time.monotonic()
    if left > 0:
        stop.wait(left)
    return not stop.is_set()


WAYS: dict[str, Callable[[float, threading.Event], bool]] = {"plain": plain, "sharp": wait_until}


def lateness(way: Callable[[float, threading.Event], bool], rate: float) -> tuple[list[float], float]:
    """Each of ``FRAMES`` waits' lateness (us), on a thread of its own, and that thread's CPU (cores)."""
    result: dict[str, Any] = {}

    def run() -> None:
        stop, late = threading.Event(), []
        cpu = time.thread_time()
        due = time.monotonic() + 1.0 / rate
        for _ in range(FRAMES):
            way(due, stop)
            late.append((time.monotonic() - due) * 1e6)
            due += 1.0 / rate
        result["late"], result["cores"] = late, (time.thread_time() - cpu) * rate / FRAMES

    thread = threading.Thread(target=run)
    thread.start()
    thread.join()
    return result["late"], result["cores"]


def bench_pacing() -> list[dict[str, Any]]:
    lines = []
    for condition in ("idle", "busy"):
        for rate in RATES:
            late: dict[str, list[float]] = {name: [] for name in WAYS}
            cores: dict[str, list[float]] = {name: [] for name in WAYS}
            for round_ in range(ROUNDS):
                for name in (list(WAYS) if round_ % 2 == 0 else list(WAYS)[::-1]):
                    if condition == "busy":
                        with busy():
                            waits, used = lateness(WAYS[name], rate)
                    else:
                        waits, used = lateness(WAYS[name], rate)
                    late[name] += waits
                    cores[name].append(used)
            for name in WAYS:
                p50, p90, p99 = np.percentile(late[name], [50, 90, 99])
                lines.append({"bench": "pacing", "condition": condition, "rate_hz": rate, "way": name,
                              "late_us_p50": round(float(p50), 1), "late_us_p90": round(float(p90), 1),
                              "late_us_p99": round(float(p99), 1), "early": sum(v < 0 for v in late[name]),
                              "cores": round(float(np.median(cores[name])), 4)})
    return lines


if __name__ == "__main__":
    for line in bench_pacing():
        print(json.dumps(line), flush=True)
