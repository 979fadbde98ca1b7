"""Garbage on a running node's input is counted and reported, and the node goes on serving."""

from __future__ import annotations

import random

import pytest

from protocol.codec import encode
from protocol.sensors import Image
from protocol.system import ErrorReport
from services.bus.pubsub import Inbox, Publisher, Role

from .busprobe import make_message
from .support import START_S, start_node, states, wait_live, wait_until

pytestmark = pytest.mark.integration


def test_echo_node_counts_bad_payloads_and_keeps_relaying(bus, procs, session):
    keys = bus.keys
    image_key = keys.image("cam0")
    reports = Inbox(session, keys.errors("echo"), ErrorReport, Role.RESULT)
    echoed = Inbox(session, keys.echo("cam0"), Image, Role.RESULT)
    node = start_node(procs, "echo", "echo", camera="cam0")
    wait_live(session, keys, {"echo"}, [node])
    raw = session.declare_publisher(image_key)

    def decode_errors() -> int:
        stats = states(session, keys).get("echo")
        return stats.decode_errors if stats else 0

    try:
        wait_until(lambda: raw.matching_status.matching, START_S, "the echo node to subscribe to its input")
        bad_payloads = [
            random.Random(7).randbytes(4096),  # random bytes
            encode(make_message("pose", 3)),  # a valid message of the wrong schema
            encode(make_message("image", 0, 64, 48))[:200],  # a truncated frame
        ]
        # One at a time: the node's input is latest-wins, so a burst could be dropped before decoding.
        for n, payload in enumerate(bad_payloads, start=1):
            raw.put(payload)
            wait_until(lambda n=n: decode_errors() >= n, START_S, f"decode error {n} to be counted")
    finally:
        raw.undeclare()

    stats = states(session, keys)["echo"]
    assert stats.decode_errors == len(bad_payloads)
    assert stats.skipped == {"decode_error": len(bad_payloads)}
    assert (stats.published, stats.processed) == (0, 0)
    assert stats.pid == node.pid
    stream = next(s for s in stats.streams if s.key == image_key)
    assert (stream.direction, stream.decode_errors) == ("in", len(bad_payloads))

    report = reports.recv(START_S)
    assert report is not None, "no ErrorReport on the node's errors key"
    assert (report.message.node, report.message.kind, report.message.key) == ("echo", "decode_error", image_key)
    assert "cannot decode" in report.message.detail

    # The node is still serving: good frames published now come out on the echo key, intact.
    frames = Publisher(session, image_key, Image, Role.FRAME)
    try:
        for i in range(5):
            frame = make_message("image", i, 64, 48)
            frames.put(frame)
            got = echoed.recv(START_S)
            assert got is not None, f"frame {i} was not relayed after the bad payloads"
            assert got.message == frame
    finally:
        frames.close()
    assert node.poll() is None, node.describe()
    # The node counts a frame as published once its put returned, which may be after the frame arrived here.
    stats = wait_until(lambda: (s := states(session, keys)["echo"]).published == 5 and s, START_S, "5 published")
    assert stats.decode_errors == len(bad_payloads)


def test_take_newest_decodes_the_newest_payload_only_and_falls_back_past_garbage(bus, session):
    """A state that each message replaces (a camera's calibration, sent with every frame) is taken newest first:
    the older payloads are let go without being decoded, and a newest one that does not decode is counted and
    the one before it taken."""
    inbox = Inbox(session, bus.keys.image("cam0"), Image, Role.RESULT)
    key = bus.keys.image("cam0")
    inbox.offer(key, b"\x00an older payload that would not decode either")
    for seq in range(1, 4):
        inbox.offer(key, encode(make_message("image", seq, 64, 48)))
    inbox.offer(key, b"\x00garbage")
    taken = inbox.take_newest()
    assert taken is not None and taken.message.header.seq == 3
    assert inbox.counter.decode_errors == 1 and inbox.pending() == 0  # the older garbage was never decoded
    assert inbox.take_newest() is None
    inbox.offer(key, encode(make_message("image", 4, 64, 48)))
    inbox.offer(key, encode(make_message("image", 5, 64, 48)))
    assert inbox.take_newest().message.header.seq == 5 and inbox.counter.decode_errors == 1
