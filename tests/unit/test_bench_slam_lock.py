"""The SLAM benchmark's timed map lock: it counts the owner thread's waits for another holder, nothing else."""

from __future__ import annotations

import threading
import time

from tests.bench.slam_tracking import TimedLock

HOLD_S = 0.05


def test_the_owner_waiting_for_another_thread_is_counted() -> None:
    lock = TimedLock(threading.RLock(), threading.get_ident())
    held, release = threading.Event(), threading.Event()

    def hold() -> None:
        with lock:
            held.set()
            release.wait()
            time.sleep(HOLD_S)

    holder = threading.Thread(target=hold)
    holder.start()
    held.wait()
    release.set()
    with lock:
        pass
    holder.join()
    assert lock.waited_ms >= 0.8 * HOLD_S * 1e3


def test_free_re_entrant_and_other_threads_acquires_are_not_counted() -> None:
    lock = TimedLock(threading.RLock(), threading.get_ident())
    with lock, lock:
        pass

    def take() -> None:
        with lock:
            pass

    other = threading.Thread(target=take)
    with lock:
        other.start()
        time.sleep(HOLD_S)
    other.join()
    assert lock.waited_ms == 0.0
