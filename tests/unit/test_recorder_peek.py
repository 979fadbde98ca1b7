"""``peek.identify``: a payload's message type and stamp from its first bytes, for both layouts."""

from __future__ import annotations

import json
import struct

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from strategies import MESSAGES

from protocol import Header, Image, Pose, encode
from protocol.codec import MAGIC
from services.recorder.peek import identify

any_message = st.sampled_from(sorted(MESSAGES)).flatmap(MESSAGES.__getitem__)


@settings(max_examples=200, deadline=None)
@given(any_message)
def test_every_encoded_message_is_identified_with_its_stamp(message):
    identity = identify(encode(message))
    assert identity.cls is type(message) and identity.reason == ""
    assert identity.stamp_ns == message.header.stamp_ns


def test_json_written_by_another_encoder_with_spaces_is_identified():
    document = {"schema": "artrack.Pose", "version": 1, "header": {"stamp_ns": 42, "frame_id": "w", "seq": 0},
                "child_frame_id": "x"}
    identity = identify(json.dumps(document, indent=2).encode())
    assert (identity.cls, identity.stamp_ns) == (Pose, 42)
    reordered = json.dumps({"schema": "artrack.Pose", "version": 1, "child_frame_id": "x",
                            "header": {"stamp_ns": 42}}).encode()
    assert (identify(reordered).cls, identify(reordered).stamp_ns) == (Pose, None)  # stamp not where expected


def test_payloads_that_are_not_known_messages_say_why():
    pose = Pose(header=Header(stamp_ns=5), child_frame_id="x")
    image = Image(header=Header(stamp_ns=5), encoding="mono8", data=np.zeros((2, 2), np.uint8))
    frame = encode(image)
    pose_as_frame = MAGIC + struct.pack("<B3sI", 1, bytes(3), 100) + encode(pose)
    cases = {
        b"": "neither an artrack frame nor JSON",
        b"\x00\x01garbage": "neither an artrack frame nor JSON",
        b'{"x": 1}': "neither an artrack frame nor JSON",
        encode(pose).replace(b'"version":1', b'"version":7'): "artrack.Pose version 7 (this build knows version 1)",
        encode(pose).replace(b"artrack.Pose", b"acme.Pose"): "unknown schema 'acme.Pose'",
        frame[12:]: "artrack.Image sent as JSON, but it travels the other way",
        pose_as_frame: "artrack.Pose sent as frame, but it travels the other way",
        frame[:8]: "truncated frame preamble",
        frame[:4] + b"\x09" + frame[5:]: "unknown frame layout",
    }
    for payload, reason in cases.items():
        identity = identify(payload)
        assert identity.cls is None and reason in identity.reason, (payload[:40], identity)


def test_identify_reads_only_the_prefix_of_a_large_frame():
    frame = encode(Image(header=Header(stamp_ns=7), encoding="bgr8", data=np.zeros((480, 640, 3), np.uint8)))
    assert len(frame) > 900_000
    assert identify(frame).cls is Image
    assert identify(frame[:200]).cls is Image  # the arrays are never looked at
