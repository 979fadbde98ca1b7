"""Typed messages cross from one real process to another over Zenoh, complete, in order, intact."""

from __future__ import annotations

import time

import pytest

from protocol.poses import Pose
from protocol.sensors import Image
from services.bus.pubsub import Inbox, Role
from services.bus.session import open_session

from .busprobe import make_message
from .support import START_S, probe_argv, published, wait_until

pytestmark = pytest.mark.integration

CASES = {
    # kind, count, probe options: many small JSON messages, and big binary frames (bgr8 + mono16)
    "pose": ("pose", 300, []),
    "image": ("image", 24, ["--width", "640", "--height", "480"]),
}


@pytest.mark.parametrize("mode", ["peer", "client"])
@pytest.mark.parametrize("case", sorted(CASES))
def test_published_messages_arrive_complete_in_order_and_equal(bus, procs, mode, case):
    kind, count, options = CASES[case]
    cls = {"pose": Pose, "image": Image}[kind]
    config = bus.config.model_copy(update={"mode": mode})
    session = open_session(config)
    try:
        key = f"{bus.keys.prefix}/probe/{kind}"
        inbox = Inbox(session, key, cls, Role.RESULT)
        peer = ["--peer", str(session.info.zid())] if mode == "peer" else []
        publisher = procs.start(probe_argv(kind, str(count), "--key", key, "--role", "result", *peer, *options),
                                name=f"publish-{kind}", env={"ARTRACK_MODE": mode})
        received = []
        deadline = time.monotonic() + START_S + 20.0
        while len(received) < count and time.monotonic() < deadline:
            got = inbox.recv(0.2)
            if got is not None:
                received.append(got.message)
            elif publisher.poll() not in (None, 0):
                break
        assert wait_until(lambda: published(publisher), 10, "the probe to finish publishing") == count

        seqs = [m.header.seq for m in received]
        assert seqs == list(range(count)), (f"received {len(seqs)} of {count}, in this order: {seqs}; "
                                            f"inbox counts: {inbox.counter.snapshot()}")
        expected = [make_message(kind, i, *_size(options)) for i in range(count)]
        for got, want in zip(received, expected, strict=True):
            assert got == want, f"message {want.header.seq} changed on the way"
        assert inbox.recv(0.3) is None, "a message arrived twice"
        counts = inbox.counter.snapshot()
        assert (counts.messages, counts.dropped, counts.decode_errors) == (count, 0, 0)
        inbox.close()  # the probe leaves once nothing subscribes any more
        assert publisher.wait(10) == 0, publisher.describe()
    finally:
        session.close()


def _size(options: list[str]) -> tuple[int, int]:
    values = dict(zip(options[::2], options[1::2], strict=True))
    return int(values.get("--width", 320)), int(values.get("--height", 240))
