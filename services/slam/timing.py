"""Milliseconds spent per stage, summed into a dict."""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager

__all__ = ["stage_timer"]


@contextmanager
def stage_timer(timings: dict[str, float], stage: str) -> Iterator[None]:
    """Adds the milliseconds spent in the ``with`` block to ``timings[stage]``."""
    start = time.perf_counter()
    try:
        yield
    finally:
        timings[stage] = timings.get(stage, 0.0) + (time.perf_counter() - start) * 1000.0
