"""The process's outbox: each thread's sends leave in the order it put them, off its thread when deferred."""

from __future__ import annotations

import threading
import time

from services.bus.outbox import Outbox


def test_a_deferred_send_returns_before_it_has_run_and_leaves_on_the_outbox_thread():
    outbox = Outbox()
    release, ran_on = threading.Event(), []

    def slow() -> None:
        release.wait(2.0)
        ran_on.append(threading.current_thread().name)

    started = time.perf_counter()
    outbox.send(slow, defer=True)
    assert time.perf_counter() - started < 0.5
    assert ran_on == []
    release.set()
    assert outbox.flush(2.0)
    assert ran_on == ["outbox"]
    outbox.close()


def test_a_send_not_deferred_waits_behind_the_queued_ones_so_order_holds():
    outbox = Outbox()
    order: list[str] = []
    gate = threading.Event()
    outbox.send(lambda: (gate.wait(2.0), order.append("frame 1")), defer=True)
    outbox.send(lambda: order.append("frame 2"), defer=True)
    outbox.send(lambda: order.append("end of stream"), defer=False)
    assert order == []
    gate.set()
    assert outbox.flush(2.0)
    assert order == ["frame 1", "frame 2", "end of stream"]
    outbox.close()


def test_another_threads_send_does_not_wait_behind_the_sends_this_thread_queued():
    outbox = Outbox()
    order: list[str] = []
    gate = threading.Event()
    outbox.send(lambda: (gate.wait(2.0), order.append("frame encoded for a recorder")), defer=True)
    other = threading.Thread(target=lambda: outbox.send(lambda: order.append("another node's result"), defer=False))
    other.start()
    other.join(2.0)
    assert order == ["another node's result"]  # sent on its own thread while the frame still waits
    gate.set()
    assert outbox.flush(2.0)
    assert order == ["another node's result", "frame encoded for a recorder"]
    outbox.close()


def test_with_nothing_queued_a_send_not_deferred_runs_on_the_callers_thread_and_raises_there():
    outbox = Outbox()
    threads: list[str] = []
    outbox.send(lambda: threads.append(threading.current_thread().name), defer=False)
    assert threads == [threading.current_thread().name]

    def broken() -> None:
        raise RuntimeError("session closed")

    try:
        outbox.send(broken, defer=False)
    except RuntimeError as exc:
        assert "session closed" in str(exc)
    else:
        raise AssertionError("an inline send's error must reach its publisher")


def test_a_failing_deferred_send_is_counted_and_the_ones_after_it_still_leave():
    outbox = Outbox()
    order: list[int] = []

    def broken() -> None:
        raise RuntimeError("session closed")

    outbox.send(broken, defer=True)
    outbox.send(lambda: order.append(2), defer=True)
    assert outbox.flush(2.0)
    assert outbox.failed == 1 and order == [2]
    outbox.close()


def test_a_full_outbox_holds_the_publisher_until_a_send_has_left():
    outbox = Outbox(depth=2)
    gate, taken = threading.Event(), threading.Event()
    outbox.send(lambda: (taken.set(), gate.wait(2.0)), defer=True)
    assert taken.wait(2.0)
    outbox.send(lambda: None, defer=True)
    outbox.send(lambda: None, defer=True)
    third_put = threading.Event()
    putter = threading.Thread(target=lambda: (outbox.send(lambda: None, defer=True), third_put.set()))
    putter.start()
    assert not third_put.wait(0.2)
    gate.set()
    assert third_put.wait(2.0)
    putter.join()
    outbox.close()


def test_close_sends_what_waits_and_later_sends_run_inline():
    outbox = Outbox()
    order: list[str] = []
    outbox.send(lambda: (time.sleep(0.05), order.append("queued")), defer=True)
    outbox.close()
    assert order == ["queued"]
    outbox.send(lambda: order.append(threading.current_thread().name), defer=True)
    assert order == ["queued", threading.current_thread().name]


def test_sends_from_several_threads_each_leave_once_and_each_thread_in_its_own_order():
    outbox = Outbox(depth=4)
    sent: list[tuple[int, int]] = []

    def publisher(k: int) -> None:
        for i in range(200):
            outbox.send(lambda k=k, i=i: sent.append((k, i)), defer=i % 3 != 0)

    threads = [threading.Thread(target=publisher, args=(k,)) for k in range(3)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert outbox.flush(2.0)
    assert sorted(sent) == [(k, i) for k in range(3) for i in range(200)]
    for k in range(3):
        assert [i for kk, i in sent if kk == k] == list(range(200))
    outbox.close()
