"""Replay control messages: the request and the status travel through the codec both ways, and
what is not a well-formed request is refused with one DecodeError."""

from __future__ import annotations

import json

import pytest

from protocol import DecodeError, Header, Pose, ReplayCommand, ReplayControl, ReplayStatus, decode, encode
from services.recorder.replay_node import control_request


@pytest.mark.parametrize("command", list(ReplayCommand))
def test_a_request_travels_as_json_naming_its_command(command: ReplayCommand):
    payload = encode(ReplayControl(header=Header(stamp_ns=5), command=command))
    assert json.loads(payload)["command"] == command.value
    assert decode(payload) == ReplayControl(header=Header(stamp_ns=5), command=command)
    assert control_request(payload).command is command


def test_a_request_without_a_command_asks_for_the_status():
    payload = json.dumps({"schema": "artrack.ReplayControl", "version": 1, "header": {"stamp_ns": 1}}).encode()
    assert control_request(payload).command is ReplayCommand.STATUS


def test_a_status_round_trips():
    status = ReplayStatus(header=Header(stamp_ns=9), node="replay", path="/tmp/a.mcap", state="paused", played=3,
                          passes=1, position_s=0.25, rate=2.0)
    assert decode(encode(status)) == status
    assert json.loads(encode(status))["state"] == "paused"


@pytest.mark.parametrize(("payload", "reason"), [
    (b"cmd=pause", "neither an artrack frame nor JSON"),
    (b"", "neither an artrack frame nor JSON"),
    (b'{"schema":"artrack.ReplayControl","version":1,"header":{"stamp_ns":1},"command":"rewind"}',
     "command: Input should be 'pause', 'resume', 'step' or 'status'"),
    (b'{"schema":"artrack.ReplayControl","version":2,"header":{"stamp_ns":1}}', "version 2 is not understood"),
    (encode(Pose(header=Header(stamp_ns=1), child_frame_id="x")), "not a control request"),
])
def test_what_is_not_a_request_is_refused_naming_why(payload: bytes, reason: str):
    with pytest.raises(DecodeError, match=reason):
        control_request(payload)
