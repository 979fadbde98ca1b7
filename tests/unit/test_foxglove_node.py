"""The Foxglove node's server in process: images gated per topic by their stamps, a taken port refused."""

from __future__ import annotations

import socket

import numpy as np
import pytest

from protocol import Header, Image, Pose
from services.runtime.node import NodeError
from services.viewer.foxglove_node import Params, Server

BASE_NS = 1_700_000_000_000_000_000


def image(camera: str, stamp_ns: int) -> Image:
    return Image(header=Header(stamp_ns=stamp_ns, frame_id=camera), encoding="mono8", data=np.zeros((4, 6), np.uint8))


def test_images_are_limited_per_topic_and_other_messages_are_not():
    server = Server(Params(port=0, image_hz=10), "test")
    try:
        for i in range(9):  # 30 fps for 0.3 s: three 100 ms slots per camera
            for camera in ("cam0", "cam1"):
                server.log(image(camera, BASE_NS + i * 33_333_333))
        assert server.sent == 2 * 3
        server.log(image("cam0", BASE_NS + 8 * 33_333_333))  # a repeat of the last frame
        assert server.sent == 6
        for i in range(4):
            server.log(Pose(header=Header(stamp_ns=BASE_NS + i, frame_id="cam0"), child_frame_id="marker/3"))
        assert server.sent == 6 + 4 * 2  # a PoseInFrame and a transform each
    finally:
        server.stop()


def test_a_taken_port_is_refused_in_one_line():
    with socket.create_server(("127.0.0.1", 0)) as taken:
        port = taken.getsockname()[1]
        with pytest.raises(NodeError, match=f"cannot serve Foxglove on 127.0.0.1:{port}"):
            Server(Params(port=port), "test")
