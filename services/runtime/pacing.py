"""Waiting for a due time with the kernel's timer slack out of the way, for the sources that pace their frames.

A thread asleep until a given time wakes late: by the kernel's timer slack (50 us by default on Linux, by
which it may defer a timer to batch wake-ups) and by the time the machine takes to run the thread again. A
paced source's frame carries its due time as its stamp, so each microsecond it goes out late is latency that
every node and app downstream counts. ``wait_until`` sets its thread's timer slack to 1 ns (``sharpen``, Linux;
elsewhere it does nothing) the first time the thread waits, then sleeps on an event until the due time.

It sleeps rather than spins for the last fraction of a millisecond: a thread that stays runnable for the last
0.25 ms (yielding or spinning) did go out 1-16 us late at the median instead of 76-157 us, but on cores busy with
other processes the scheduler then took the core from it for a whole time slice in one or two waits of a
hundred, 3.3-3.6 ms late against 0.6 ms for a sleep (docs/benchmarks.md, "Pacing").
"""

from __future__ import annotations

import ctypes
import functools
import sys
import threading
import time
from collections.abc import Callable

__all__ = ["sharpen", "timer_slack_ns", "wait_until"]

_PR_SET_TIMERSLACK, _PR_GET_TIMERSLACK = 29, 30
_local = threading.local()


@functools.cache
def _prctl() -> Callable[..., int] | None:
    """libc's ``prctl`` on Linux, else None."""
    if not sys.platform.startswith("linux"):
        return None
    return ctypes.CDLL(None, use_errno=True).prctl


def sharpen() -> None:
    """Ask the kernel to wake the calling thread's timed waits with a slack of 1 ns (Linux)."""
    prctl = _prctl()
    if prctl is not None:
        prctl(_PR_SET_TIMERSLACK, 1, 0, 0, 0)


def timer_slack_ns() -> int | None:
    """The calling thread's timer slack (ns) on Linux, else None."""
    prctl = _prctl()
    return None if prctl is None else int(prctl(_PR_GET_TIMERSLACK, 0, 0, 0, 0))


def wait_until(due: float, stop: threading.Event) -> bool:
    """Sleep until ``time.monotonic()`` reaches ``due`` (at once when it has), or until ``stop`` is set; whether
    ``stop`` is still clear. The calling thread's timer slack is 1 ns from its first call on."""
    if not getattr(_local, "sharp", False):
        sharpen()
        _local.sharp = True
    left = due - time.monotonic()
    if left > 0.0:
        stop.wait(left)
    return not stop.is_set()
