"""The Foxglove node's outputs in process: served images gated per topic by their stamps, static data sent again
to a client that subscribes after it was logged, a taken port refused, the file written whole and in log-time
order, and the options that name neither or an existing file refused."""

from __future__ import annotations

import base64
import json
import socket
import time
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from pydantic import ValidationError
from websockets.sync.client import connect

from protocol import Header, Image, ImageTarget, ImageTargets, Pose
from services.runtime.node import NodeError
from services.viewer.foxglove_node import KIND, Outputs, Params
from tests.foxglove_decoding import decoded

BASE_NS = 1_700_000_000_000_000_000


def image(camera: str, stamp_ns: int) -> Image:
    return Image(header=Header(stamp_ns=stamp_ns, frame_id=camera), encoding="mono8", data=np.zeros((4, 6), np.uint8))


def test_images_are_limited_per_topic_and_other_messages_are_not():
    outputs = Outputs(Params(port=0, image_hz=10), "test")
    try:
        for i in range(9):  # 30 fps for 0.3 s: three 100 ms slots per camera
            for camera in ("cam0", "cam1"):
                outputs.log(image(camera, BASE_NS + i * 33_333_333))
        assert outputs.sent == 2 * 3
        outputs.log(image("cam0", BASE_NS + 8 * 33_333_333))  # a repeat of the last frame
        assert outputs.sent == 6
        for i in range(4):
            outputs.log(Pose(header=Header(stamp_ns=BASE_NS + i, frame_id="cam0"), child_frame_id="marker/3"))
        assert outputs.sent == 6 + 4 * 2  # a PoseInFrame and a transform each
        assert outputs.written == 0
    finally:
        outputs.close()


def test_a_client_that_subscribes_late_gets_the_targets_outlines_logged_before_it_came():
    outputs = Outputs(Params(port=0), "test")
    corners = ((-0.04, 0.03, 0.0), (0.04, 0.03, 0.0), (0.04, -0.03, 0.0), (-0.04, -0.03, 0.0))
    try:
        outputs.log(ImageTargets(header=Header(stamp_ns=BASE_NS, frame_id="cam0"), targets=(
            ImageTarget(name="card", frame_id="target/card", width_m=0.08, height_m=0.06, corners=corners),)))
        outputs.log(Pose(header=Header(stamp_ns=BASE_NS, frame_id="cam0"), child_frame_id="target/card"))
        assert outputs.server is not None
        got = None
        with connect(f"ws://127.0.0.1:{outputs.server.port}", subprotocols=["foxglove.sdk.v1"]) as client:
            deadline = time.monotonic() + 5.0
            while got is None and time.monotonic() < deadline:
                try:
                    frame = client.recv(timeout=0.2)
                except TimeoutError:
                    continue
                if isinstance(frame, str):
                    control = json.loads(frame)
                    if control["op"] == "advertise":
                        channel = next(c for c in control["channels"] if c["topic"] == "/cam0/target_outlines")
                        client.send(json.dumps({"op": "subscribe", "subscriptions": [
                            {"id": 1, "channelId": channel["id"]}]}))
                else:  # opcode, subscription id (uint32), log time (uint64), payload
                    got = decoded(channel["schemaName"], base64.b64decode(channel["schema"]), bytes(frame[13:]))
    finally:
        outputs.close()
    assert got is not None, "no outlines came"
    (entity,) = got.entities
    assert entity.frame_id == "target/card" and len(entity.lines[0].points) == 4


def test_a_taken_port_is_refused_in_one_line():
    with socket.create_server(("127.0.0.1", 0)) as taken:
        port = taken.getsockname()[1]
        with pytest.raises(NodeError, match=f"cannot serve Foxglove on 127.0.0.1:{port}"):
            Outputs(Params(port=port), "test")


def test_the_file_gets_every_image_in_log_time_order_while_the_server_gets_its_rate(tmp_path: Path):
    out = tmp_path / "live.mcap"
    outputs = Outputs(Params(port=0, image_hz=10, mcap=out), "test")
    try:
        for i in range(9):
            outputs.log(image("cam0", BASE_NS + i * 33_333_333))
            outputs.log(Pose(header=Header(stamp_ns=BASE_NS + i * 33_333_333, frame_id="cam0"),
                             child_frame_id="marker/3"))
        assert (outputs.sent, outputs.written) == (3 + 9 * 2, 9 * 3)
    finally:
        outputs.close()
    with open(out, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None and summary.statistics.chunk_count >= 1
        topics = {c.id: c.topic for c in summary.channels.values()}
        counts = {topics[c]: n for c, n in summary.statistics.channel_message_counts.items()}
        assert counts == {"/cam0/image": 9, "/pose/cam0/marker/3": 9, "/tf": 9}
        read = list(reader.iter_messages(log_time_order=False))
    log_times = [m.log_time for _, _, m in read]
    assert log_times == sorted(log_times)
    stamps = [decoded(s.name, s.data, m.data).timestamp.ToNanoseconds() for s, c, m in read
              if c.topic == "/cam0/image"]
    assert stamps == [BASE_NS + i * 33_333_333 for i in range(9)]


def test_a_file_alone_serves_nothing(tmp_path: Path):
    outputs = Outputs(Params(serve=False, mcap=tmp_path / "live.mcap"), "test")
    try:
        assert outputs.server is None
        outputs.log(image("cam0", BASE_NS))
        assert (outputs.sent, outputs.written) == (0, 1)
    finally:
        outputs.close()
    assert (tmp_path / "live.mcap").stat().st_size > 0


def test_options_that_name_no_output_are_refused():
    with pytest.raises(ValidationError, match="give `mcap`"):
        Params(serve=False)


def test_an_existing_file_is_refused_unless_forced(tmp_path: Path):
    out = tmp_path / "live.mcap"
    out.write_bytes(b"kept")
    with pytest.raises(ValueError, match="exists: give --force"):
        KIND.preflight(Params(mcap=out, serve=False))
    with pytest.raises(NodeError, match=f"cannot write {out}"):
        Outputs(Params(mcap=out, serve=False), "test")
    assert out.read_bytes() == b"kept"
    KIND.preflight(Params(mcap=out, serve=False, force=True))
    Outputs(Params(mcap=out, serve=False, force=True), "test").close()
    assert out.read_bytes() != b"kept"


def test_a_missing_folder_is_refused_before_start(tmp_path: Path):
    with pytest.raises(ValueError, match="does not exist"):
        KIND.preflight(Params(mcap=tmp_path / "nowhere" / "live.mcap"))


def test_the_file_is_the_node_s_sink_output(tmp_path: Path):
    assert KIND.sink is not None
    assert KIND.sink.files(Params(mcap=tmp_path / "f.mcap")) == (("foxglove recording", tmp_path / "f.mcap"),)
    assert KIND.sink.files(Params()) == ()
