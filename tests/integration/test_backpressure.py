"""A slow consumer under a flood: frames are latest-wins and counted, results are all kept in order."""

from __future__ import annotations

import logging
import threading
import time

import pytest

from protocol.sensors import Image
from services.bus.pubsub import Inbox, Role

from .busprobe import make_message
from .support import START_S, probe_argv, published, wait_until

pytestmark = pytest.mark.integration

SMALL = ["--width", "64", "--height", "48"]


class PendingWatch:
    """Samples ``inbox.pending()`` from a thread while the test consumes; keeps the maximum."""

    def __init__(self, inbox: Inbox):
        self.inbox = inbox
        self.max = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        while not self._stop.is_set():
            self.max = max(self.max, self.inbox.pending())
            time.sleep(0.0005)

    def __enter__(self) -> PendingWatch:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()


def _flood(procs, session, key: str, role: str, count: int, rate: float):
    return procs.start(probe_argv("image", str(count), "--key", key, "--role", role, "--rate", str(rate),
                                  "--peer", str(session.info.zid()), *SMALL), name=f"flood-{role}")


def test_slow_frame_subscriber_keeps_only_the_newest_and_counts_drops(bus, procs, session):
    count = 400
    key = f"{bus.keys.prefix}/probe/frames"
    frames = Inbox(session, key, Image, Role.FRAME)  # depth 1: latest wins
    witness = Inbox(session, key, Image, Role.RESULT)  # a fast reference: everything that arrived
    assert frames.depth == 1
    publisher = _flood(procs, session, key, "frame", count, rate=500)
    taken = []
    last_count, last_change = 0, time.monotonic()
    with PendingWatch(frames) as watch:
        deadline = time.monotonic() + START_S + 20.0
        while time.monotonic() < deadline:
            watch.max = max(watch.max, frames.pending())
            got = frames.take()
            if got is not None:
                taken.append(got.message)
            witness.latest()  # keep the reference queue drained
            if frames.counter.messages != last_count:
                last_count, last_change = frames.counter.messages, time.monotonic()
            elif got is None and published(publisher) and time.monotonic() - last_change > 0.5:
                break  # the source is done and nothing has arrived for a while
            time.sleep(0.02)  # the slow consumer: 50 takes a second against 500 frames a second
    assert published(publisher) == count, publisher.describe()

    arrived = witness.counter.snapshot().messages
    counts = frames.counter.snapshot()
    seqs = [m.header.seq for m in taken]
    assert arrived > count // 2, f"only {arrived} of {count} frames reached this process"
    assert counts.messages == arrived
    assert watch.max <= frames.depth, f"the frame queue held {watch.max} > depth {frames.depth}"
    assert counts.dropped > 0, "a consumer 10x slower than the source dropped nothing"
    assert len(taken) + counts.dropped + frames.pending() == arrived
    assert len(taken) < arrived
    assert seqs == sorted(set(seqs)), "frames went backwards or repeated"
    assert seqs[-1] == witness.latest().message.header.seq, "the newest frame was not the one kept"
    for message in taken:
        assert message == make_message("image", message.header.seq, 64, 48)
    frames.close()
    witness.close()
    assert publisher.wait(10) == 0, publisher.describe()


def test_slow_result_subscriber_gets_every_message_in_order(bus, procs, session):
    count = 300
    key = f"{bus.keys.prefix}/probe/results"
    results = Inbox(session, key, Image, Role.RESULT)
    publisher = _flood(procs, session, key, "result", count, rate=0)
    taken = []
    with PendingWatch(results) as watch:
        deadline = time.monotonic() + START_S + 20.0
        while len(taken) < count and time.monotonic() < deadline:
            got = results.recv(0.2)
            if got is not None:
                taken.append(got.message)
                time.sleep(0.003)  # slow, but the queue is deep enough for the whole flood
    assert published(publisher) == count, publisher.describe()
    assert watch.max > 10, "the consumer was never behind: this test did not test a slow consumer"
    assert [m.header.seq for m in taken] == list(range(count))
    assert results.counter.snapshot().dropped == 0
    assert taken == [make_message("image", i, 64, 48) for i in range(count)]
    results.close()
    assert publisher.wait(10) == 0, publisher.describe()


def test_result_overflow_is_counted_and_logged_not_silent(bus, procs, session, caplog):
    count, depth = 200, 20
    key = f"{bus.keys.prefix}/probe/overflow"
    results = Inbox(session, key, Image, Role.RESULT, depth=depth)
    caplog.set_level(logging.WARNING, logger="services.bus.pubsub")
    publisher = _flood(procs, session, key, "result", count, rate=0)
    wait_until(lambda: published(publisher), START_S + 20.0, "the flood")  # nobody takes meanwhile

    wait_until(lambda: results.counter.messages >= count, 10, f"all {count} results to arrive")
    counts = results.counter.snapshot()
    assert counts.messages == count
    assert results.pending() == depth
    assert counts.dropped == count - depth
    kept = []
    while (got := results.take()) is not None:
        kept.append(got.message.header.seq)
    assert kept == list(range(count - depth, count)), "overflow must drop the oldest and keep order"
    warnings = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING and key in r.getMessage()]
    assert warnings, "results were dropped without a word in the log"
    results.close()
    assert publisher.wait(10) == 0, publisher.describe()
