"""The benchmark's output lines: figures per variant, typed-versus-raw comparisons, the machine;
and the order and pairing helpers the benchmarks that compare variants share.

A variant's figure is the median of its runs. A comparison pairs run i of typed with run i
of raw (measured back to back, in alternating order) and takes the median over the pairs of
the typed/raw throughput ratio and of the typed - raw p50 latency difference, so that a
slow spell of the machine hits both members of a pair rather than one variant.
"""

from __future__ import annotations

import operator
import os
import platform
import statistics
from collections.abc import Callable, Sequence
from importlib.metadata import version
from typing import Any, TypeVar

from tests.bench.runs import Run
from tests.bench.scenes import yardstick

THROUGHPUT_RATIO_TARGET = 0.9
LATENCY_DELTA_TARGET_US = 100.0

T = TypeVar("T")


def alternating(variants: Sequence[T], rounds: int) -> list[tuple[int, T]]:
    """``(round, variant)`` in measuring order: each variant once a round, the order reversed every
    other round (A B, B A, A B, ...), so a drift of the machine hits every variant alike."""
    return [(round_, variant) for round_ in range(rounds)
            for variant in (variants if round_ % 2 == 0 else variants[::-1])]


def paired_median(first: Sequence[float], second: Sequence[float],
                  combine: Callable[[float, float], float] = operator.truediv) -> float:
    """Median over i of ``combine(first[i], second[i])`` (default the ratio), for figures measured
    in pairs; ValueError when the sequences differ in length or are empty."""
    if not first or len(first) != len(second):
        raise ValueError(f"need two equally long, non-empty sequences, not {len(first)} and {len(second)}")
    return statistics.median(combine(a, b) for a, b in zip(first, second, strict=True))


def variant_line(bench: str, variant: str, payload_bytes: int, runs: list[Run]) -> dict[str, Any]:
    """Medians over ``runs`` of one variant, with the per-run throughput and p50 for spread."""
    return {
        "bench": bench,
        "variant": variant,
        "payload_bytes": payload_bytes,
        "msg_per_s": round(statistics.median(r.msg_per_s for r in runs), 1),
        "latency_p50_us": round(statistics.median(r.latency_p50_us for r in runs), 1),
        "latency_p99_us": round(statistics.median(r.latency_p99_us for r in runs), 1),
        "n": min(r.latency_n for r in runs),
        "flood_msgs": round(statistics.median(r.flood_sent for r in runs)),
        "lost": sum(r.lost for r in runs),
        "runs": len(runs),
        "msg_per_s_runs": [round(r.msg_per_s, 1) for r in runs],
        "latency_p50_us_runs": [round(r.latency_p50_us, 1) for r in runs],
    }


def comparison_lines(bench: str, typed: list[Run], raw: list[Run]) -> list[dict[str, Any]]:
    """Typed/raw throughput ratio and typed - raw p50 latency, medians over paired runs."""
    ratio = paired_median([t.msg_per_s for t in typed], [r.msg_per_s for r in raw])
    delta = paired_median([t.latency_p50_us for t in typed], [r.latency_p50_us for r in raw], operator.sub)
    return [
        {"bench": bench, "figure": "typed_vs_raw_throughput", "ratio": round(ratio, 3),
         "target": f">= {THROUGHPUT_RATIO_TARGET}", "met": ratio >= THROUGHPUT_RATIO_TARGET},
        {"bench": bench, "figure": "typed_minus_raw_latency_p50", "delta_us": round(delta, 1),
         "target": f"<= +{LATENCY_DELTA_TARGET_US:.0f} us", "met": delta <= LATENCY_DELTA_TARGET_US},
    ]


def machine_line(malloc: str, load_before: float) -> dict[str, Any]:
    """CPU model and count, Python, the package versions on the measured path, the malloc
    settings, and the 1-minute load average before and after the suite (other work on the
    cores shows there)."""
    return {
        "bench": "machine",
        "cpu": _cpu_model(),
        "cores": os.cpu_count(),
        "python": platform.python_version(),
        "zenoh": version("eclipse-zenoh"),
        "numpy": version("numpy"),
        "pydantic": version("pydantic"),
        "os": platform.platform(),
        "malloc": malloc,
        "loadavg_1m_before": round(load_before, 2),
        "loadavg_1m_after": round(os.getloadavg()[0], 2),
    }


def host(**common: Any) -> dict[str, Any]:
    """The machine line of a benchmark that runs pipelines: ``common``, the CPU model and count, the load
    average, and the ``room_fps`` yardstick (``tests.bench.scenes.yardstick``) to compare days by."""
    return {**common, "variant": "machine", "cpu": _cpu_model(), "cpus": os.cpu_count(),
            "load_average": [round(v, 2) for v in os.getloadavg()], "room_fps": yardstick()}


def _cpu_model() -> str:
    try:
        with open("/proc/cpuinfo") as cpuinfo:
            for line in cpuinfo:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"
