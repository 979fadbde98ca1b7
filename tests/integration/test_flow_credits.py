"""Credits and ends of stream between real nodes on a real Zenoh session: a lossless source waits for
every node that takes its frames, stops waiting for one that died, takes one that came back as caught
up, and a node ends only once what its upstream published has arrived."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from protocol.keys import Keys
from protocol.message import Header
from protocol.sensors import Image
from services.bus.pubsub import Role
from services.runtime.flow import Credits, FlowPlan
from services.runtime.node import Node
from tests.integration.support import START_S, wait_until

pytestmark = pytest.mark.integration

HELD_S = 0.5


def blocked(credits: Credits, seq: int) -> bool:
    """Whether frame ``seq`` is still held back after ``HELD_S``."""
    until = time.monotonic() + HELD_S
    return not credits.wait_for(seq, lambda: time.monotonic() < until)


def released(credits: Credits, seq: int) -> bool:
    until = time.monotonic() + START_S
    return credits.wait_for(seq, lambda: time.monotonic() < until)


def test_a_source_sends_a_window_ahead_of_its_slowest_node_and_no_further(bus, session):
    keys: Keys = bus.config.keys
    fast = Node("fast", "test", bus.config, flow=FlowPlan(lossless=True, acks=True))
    slow = Node("slow", "test", bus.config, flow=FlowPlan(lossless=True, acks=True))
    open_nodes = [fast, slow]
    try:
        fast.ready()  # before the source starts: its credits ask for what was acknowledged so far
        credits = Credits(session, keys, ["fast", "slow"], window=2)
        assert blocked(credits, 0)  # "slow" has not said it is ready
        slow.ready()
        for seq in (0, 1):
            assert released(credits, seq)
            credits.sent(seq)
        assert blocked(credits, 2)
        fast.ack(1)
        assert blocked(credits, 2)  # the slowest decides
        slow.ack(0)
        assert released(credits, 2)
        credits.sent(2)
        assert blocked(credits, 3)
        open_nodes.remove(slow)
        slow.close()  # gone: no longer waited for
        assert released(credits, 3)
        credits.sent(3)
        fast.ack(3)
        again = Node("slow", "test", bus.config, flow=FlowPlan(lossless=True, acks=True))
        open_nodes.append(again)
        again.ready()  # a new run of the node: caught up with what was sent while it was down
        assert released(credits, 4)
        credits.sent(4)
        credits.sent(5)
        assert blocked(credits, 6)
        again.ack(4)
        fast.ack(5)
        assert released(credits, 6)
        credits.close()
    finally:
        for node in open_nodes:
            node.close()


@pytest.mark.parametrize(("sent", "missing"), [([0, 1, 2, 3, 4, 5], 0), ([0, 1, 3, 4], 2)],
                         ids=["every frame", "frames 2 and 5 lost"])
def test_a_node_ends_after_its_upstream_and_counts_the_frames_that_never_arrived(bus, sent, missing):
    """Frames the source never put on the bus stand for frames the bus lost: a gap, and a tail after
    the last one received up to the last seq the source's end names."""
    keys: Keys = bus.config.keys
    source = Node("src", "test", bus.config, flow=FlowPlan(lossless=True, credits_from=("taker",)))
    taker = Node("taker", "test", bus.config, flow=FlowPlan(lossless=True, acks=True, upstream=("src",)))
    try:
        frames = taker.inbox(keys.image("cam0"), Image, Role.FRAME)
        served: list[int] = []
        worker = threading.Thread(target=lambda: served.extend(m.header.seq for m in taker.inputs(frames)))
        worker.start()
        credits = source.credits()
        assert credits is not None
        out = source.publisher(keys.image("cam0"), Image, Role.FRAME)
        for seq in sent:
            assert released(credits, seq)
            out.put(frame(seq))
            credits.sent(seq)
        source.end_of_stream(5, len(sent))
        wait_until(lambda: taker.ended, START_S, "the taker's end of stream")
        assert taker.stats().ended and taker.stats().missing == missing
        taker.stop()
        worker.join(START_S)
        assert served == sent
    finally:
        taker.close()
        source.close()


def frame(seq: int) -> Image:
    return Image(header=Header(stamp_ns=seq + 1, frame_id="cam0", seq=seq), encoding="mono8",
                 data=np.full((4, 4), seq, np.uint8))
