"""Waiting for a due time: the thread's timer slack made 1 ns, the wait ended by its time or by a stop."""

from __future__ import annotations

import ctypes
import sys
import threading
import time

import pytest

from services.runtime.pacing import sharpen, timer_slack_ns, wait_until

linux = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="timer slack is a Linux setting")


def loosen() -> None:
    """The calling thread's timer slack back to Linux's default, 50 us."""
    ctypes.CDLL(None, use_errno=True).prctl(29, 50_000, 0, 0, 0)


def on_thread(work):
    """``work()``'s result, run on a new thread (timer slack is kept per thread)."""
    result = []
    thread = threading.Thread(target=lambda: result.append(work()))
    thread.start()
    thread.join()
    return result[0]


@linux
def test_sharpen_sets_the_calling_threads_timer_slack_to_one_nanosecond() -> None:
    def slacks():
        loosen()
        before = timer_slack_ns()
        sharpen()
        return before, timer_slack_ns()

    assert on_thread(slacks) == (50_000, 1)


@linux
def test_a_wait_sharpens_its_own_thread_and_not_the_callers() -> None:
    def waited():
        loosen()
        wait_until(time.monotonic(), threading.Event())
        return timer_slack_ns()

    mine = timer_slack_ns()
    assert on_thread(waited) == 1
    assert timer_slack_ns() == mine


def test_a_wait_returns_once_its_time_has_come() -> None:
    stop = threading.Event()
    for delay in (0.0, 0.001, 0.004, 0.02):
        due = time.monotonic() + delay
        assert wait_until(due, stop)
        assert time.monotonic() >= due - 0.0005


def test_a_time_already_past_returns_at_once() -> None:
    started = time.monotonic()
    assert wait_until(started - 1.0, threading.Event())
    assert time.monotonic() - started < 0.5


def test_a_stop_ends_a_long_wait_and_says_so() -> None:
    stop = threading.Event()
    threading.Timer(0.05, stop.set).start()
    started = time.monotonic()
    assert not wait_until(started + 30.0, stop)
    assert time.monotonic() - started < 10.0
    assert not wait_until(time.monotonic() - 1.0, stop)
