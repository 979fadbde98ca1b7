"""``codec.peek``: a payload's class, media type and header without decoding it, cross-checked
against ``decode``; garbage and truncated payloads raise one DecodeError."""

from __future__ import annotations

import contextlib
import json
import struct
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from strategies import MESSAGES
from test_codec import FRAME_FAULTS, image, reframe

from protocol import DecodeError, Header, Image, Message, Pose, decode, encode, peek
from protocol.codec import MAGIC, MEDIA_FRAME, MEDIA_JSON, is_frame
from protocol.message import message_types

FAST = settings(max_examples=100, deadline=None)
any_message = st.sampled_from(sorted(MESSAGES)).flatmap(MESSAGES.__getitem__)


def peek_error(payload: bytes) -> DecodeError:
    with pytest.raises(DecodeError) as caught:
        peek(payload)
    return caught.value


def assert_peeks_as_decoded(payload: bytes) -> None:
    message = decode(payload)
    peeked = peek(payload)
    assert peeked.cls is type(message)
    assert (peeked.schema, peeked.version) == (message.SCHEMA, message.VERSION)
    assert peeked.media_type == (MEDIA_FRAME if is_frame(type(message)) else MEDIA_JSON)
    assert Header(stamp_ns=peeked.stamp_ns, frame_id=peeked.frame_id, seq=peeked.seq) == message.header


@pytest.mark.parametrize("schema", sorted(message_types()))
@settings(max_examples=25, deadline=None)
@given(data=st.data())
def test_every_message_kind_peeks_as_it_decodes(schema: str, data: st.DataObject):
    assert_peeks_as_decoded(encode(data.draw(MESSAGES[schema])))


@FAST
@given(message=any_message, data=st.data())
def test_every_proper_prefix_of_a_payload_is_refused_as_truncated(message: Message, data: st.DataObject):
    payload = encode(message)
    cut = data.draw(st.integers(0, len(payload) - 1))
    assert isinstance(peek_error(payload[:cut]), DecodeError)


@FAST
@given(message=any_message, data=st.data())
def test_a_payload_that_decodes_after_a_byte_changed_peeks_the_same(message: Message, data: st.DataObject):
    payload = bytearray(encode(message))
    at = data.draw(st.integers(0, len(payload) - 1))
    payload[at] = data.draw(st.integers(0, 255))
    try:
        decode(payload)
    except DecodeError:
        with contextlib.suppress(DecodeError):
            peek(bytes(payload))
        return
    assert_peeks_as_decoded(bytes(payload))


@FAST
@given(st.binary(max_size=64))
def test_garbage_raises_decode_error_and_nothing_else(payload: bytes):
    try:
        peek(payload)
    except DecodeError:
        return
    assert_peeks_as_decoded(payload)


def test_json_written_by_another_encoder_peeks_wherever_the_header_is():
    header = {"stamp_ns": 42, "frame_id": "w", "seq": 3}
    spaced = json.dumps({"schema": "artrack.Pose", "version": 1, "header": header, "child_frame_id": "x"}, indent=2)
    reordered = json.dumps({"child_frame_id": "x", "header": header, "version": 1, "schema": "artrack.Pose"})
    for payload in (spaced.encode(), reordered.encode()):
        peeked = peek(payload)
        assert (peeked.cls, peeked.stamp_ns, peeked.frame_id, peeked.seq) == (Pose, 42, "w", 3)


def test_faults_are_named():
    pose = Pose(header=Header(stamp_ns=5), child_frame_id="x")
    frame = encode(Image(header=Header(stamp_ns=5), encoding="mono8", data=np.zeros((2, 2), np.uint8)))
    frame_json = frame[12 : 12 + struct.unpack_from("<I", frame, 8)[0]]
    pose_as_frame = MAGIC + struct.pack("<B3sI", 1, bytes(3), len(encode(pose))) + encode(pose)
    cases = {
        b"": "neither an artrack frame nor JSON",
        b"\x00\x01garbage": "neither an artrack frame nor JSON",
        b"\xff\xfe{": "neither an artrack frame nor JSON",
        b'{"x": 1}': 'no "schema" name',
        encode(pose).replace(f'"version":{pose.VERSION}'.encode(), b'"version":7'):
            "version 7 is not understood (this build reads version",
        encode(pose).replace(b"artrack.Pose", b"acme.Pose"): "unknown schema 'acme.Pose'",
        encode(pose).replace(b'"stamp_ns":5', b'"stamp_ns":-5'): "header.stamp_ns: Input should be greater than",
        encode(pose).replace(b'"header"', b'"heading"'): "header: Input should be a valid dictionary",
        frame_json: "sent as JSON, but this schema travels the other way",
        pose_as_frame: "sent as frame, but this schema travels the other way",
        frame[:8]: "truncated frame preamble",
        frame[:20]: "frame header needs",
        frame[:-1]: "array 'data': needs bytes",
        frame[:4] + b"\x09" + frame[5:]: "frame layout 9 is not understood",
        frame[:12] + b"\xff" + frame[13:]: "frame header is not JSON",
    }
    for payload, reason in cases.items():
        assert reason in str(peek_error(payload)), payload[:40]


PEEKED_FRAME_FAULTS = {"unknown schema", "version 99", "sent as frame", "missing descriptor", "needs bytes",
                       "bad offset", "bad shape", "payload ends at", "not allowed"}


@pytest.mark.parametrize(("edit", "expected"), FRAME_FAULTS, ids=[e for _, e in FRAME_FAULTS])
def test_frame_header_faults_peek_finds_are_those_decode_names(edit: Callable[[dict[str, Any]], None],
                                                               expected: str):
    payload = reframe(encode(image()), edit)
    with pytest.raises(DecodeError) as decoded:
        decode(payload)
    if any(fault in expected for fault in PEEKED_FRAME_FAULTS):
        assert str(peek_error(payload)) == str(decoded.value)
    else:  # a field that does not validate: peek does not look
        assert peek(payload).cls is Image


def test_peek_does_not_validate_fields_outside_the_header():
    document = json.loads(encode(Pose(header=Header(stamp_ns=9, seq=2), child_frame_id="x")))
    document["covariance"] = [0.0] * 5
    payload = json.dumps(document).encode()
    assert "covariance" in str(pytest.raises(DecodeError, decode, payload).value)
    assert (peek(payload).cls, peek(payload).stamp_ns, peek(payload).seq) == (Pose, 9, 2)


def test_peek_takes_bytes_bytearray_and_memoryview():
    payload = encode(Image(header=Header(stamp_ns=7, seq=4), encoding="bgr8", data=np.zeros((48, 64, 3), np.uint8)))
    for given_as in (bytes, bytearray, memoryview):
        assert (peek(given_as(payload)).stamp_ns, peek(given_as(payload)).seq) == (7, 4)
