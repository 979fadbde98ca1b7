"""`artrack view --foxglove` beside a capture node, read by a WebSocket client speaking Foxglove's protocol:
advertised channels, a subscription, binary message frames decoded with the advertised protobuf schema.

foxglove-sdk 0.30 accepts the subprotocol ``foxglove.sdk.v1`` only (a client offering just
``foxglove.websocket.v1`` is refused with HTTP 400); the client offers both, as Foxglove's app does."""

from __future__ import annotations

import base64
import json
import os
import signal
import struct
import time

import numpy as np
import pytest
from websockets.sync.client import connect

from protocol import Header, Pose, Transform
from services.bus.pubsub import Publisher, Role
from services.synthetic import make_scene
from tests.conftest import free_port
from tests.foxglove_decoding import decoded

from .support import START_S, wait_live, wait_until

pytestmark = pytest.mark.integration

FRAMES, FPS, WIDTH, HEIGHT = 150, 30, 160, 120
IMAGE_TOPIC, POSE_TOPIC = "/cam0/image", "/pose/cam0/marker/3"
SUBPROTOCOLS = ["foxglove.sdk.v1", "foxglove.websocket.v1"]
RESUBSCRIBE_S = 2.0
"""A channel subscribed to that has sent nothing for this long is subscribed to again."""
MESSAGE_DATA = 0x01
"""Opcode of a binary message-data frame: opcode (1 byte), subscription id (uint32), log time (uint64 ns), payload."""


def pose(i: int) -> Pose:
    return Pose(header=Header(stamp_ns=1_700_000_000_000_000_000 + i, frame_id="cam0", seq=i),
                child_frame_id="marker/3", transform=Transform(translation=(0.01 * i, -0.1, 0.5)))


def test_the_foxglove_server_streams_images_and_poses_to_a_websocket_client(bus, procs, session):
    keys, port = bus.keys, free_port()
    server = procs.artrack("view", "--foxglove", "--port", str(port), "--image-hz", "0", name="foxglove")
    wait_live(session, keys, {"foxglove"}, [server])
    said = f"serving {keys.prefix} to Foxglove on ws://127.0.0.1:{port}"

    def listening() -> bool:
        """The node's own word that its server is bound (its token goes live before the server starts)."""
        assert server.poll() is None, server.describe()
        return said in server.stderr

    wait_until(listening, START_S, "the foxglove node to listen")
    capture = procs.artrack("node", "capture", "--name", "cam", "--params", json.dumps(
        {"source": "synthetic:markers", "fps": FPS, "frames": FRAMES, "wait_for_subscriber": True,
         "scene": {"width": WIDTH, "height": HEIGHT}}), name="cam")
    poses = Publisher(session, keys.pose("marker-3"), Pose, Role.RESULT)
    wait_until(poses.matched, START_S, "the foxglove node to subscribe")
    schemas: dict[int, str] = {}  # subscription id -> topic
    channels: dict[str, dict] = {}
    subscribed: dict[str, float] = {}  # topic -> when it was last subscribed to
    got: dict[str, object] = {}
    sent = 0
    with connect(f"ws://127.0.0.1:{port}", subprotocols=SUBPROTOCOLS, open_timeout=START_S,
                 max_size=None) as client:
        assert client.subprotocol == "foxglove.sdk.v1"

        def subscribe(topics: list[str]) -> None:
            """Subscribe to ``topics`` under fresh subscription ids (a busy server can refuse a subscription
            to a channel it has just advertised: "unknown channel"; it is then asked again)."""
            ids = {len(schemas) + 1 + k: topic for k, topic in enumerate(topics)}
            schemas.update(ids)
            subscribed.update((topic, time.monotonic()) for topic in topics)
            client.send(json.dumps({"op": "subscribe", "subscriptions": [
                {"id": sub, "channelId": channels[topic]["id"]} for sub, topic in ids.items()]}))

        deadline = time.monotonic() + START_S + FRAMES / FPS
        while len(got) < 2 and time.monotonic() < deadline:
            poses.put(pose(sent))
            sent += 1
            stale = [t for t, at in subscribed.items() if t not in got and time.monotonic() - at > RESUBSCRIBE_S]
            if stale:
                subscribe(stale)
            try:
                frame = client.recv(timeout=0.1)
            except TimeoutError:
                continue
            if isinstance(frame, str):
                control = json.loads(frame)
                wanted = [c for c in control.get("channels", ()) if control["op"] == "advertise"
                          and c["topic"] in (IMAGE_TOPIC, POSE_TOPIC) and c["topic"] not in channels]
                channels.update((c["topic"], c) for c in wanted)
                if wanted:
                    subscribe([c["topic"] for c in wanted])
            elif frame[0] == MESSAGE_DATA:
                subscription, _ = struct.unpack_from("<IQ", frame, 1)
                channel = channels[schemas[subscription]]
                assert (channel["encoding"], channel["schemaEncoding"]) == ("protobuf", "protobuf")
                got.setdefault(channel["topic"], decoded(channel["schemaName"], base64.b64decode(channel["schema"]),
                                                         bytes(frame[13:])))
    poses.close()
    assert set(got) == {IMAGE_TOPIC, POSE_TOPIC}, (sorted(channels), server.describe())
    image, posed = got[IMAGE_TOPIC], got[POSE_TOPIC]
    assert (image.width, image.height, image.encoding, image.frame_id) == (WIDTH, HEIGHT, "mono8", "cam0")
    pixels = np.frombuffer(image.data, np.uint8).reshape(HEIGHT, WIDTH)
    scene = make_scene("markers", width=WIDTH, height=HEIGHT)
    assert any(np.array_equal(pixels, scene.render(i).images["cam0"]) for i in range(FRAMES))
    i = round(posed.timestamp.nanos)
    assert posed.frame_id == "cam0" and 0 <= i < sent
    assert [posed.pose.position.x, posed.pose.position.y, posed.pose.position.z] == pytest.approx(
        pose(i).transform.translation)
    os.kill(server.pid, signal.SIGINT)
    assert server.wait(15) == 0, server.describe()
    capture.wait(START_S + FRAMES / FPS)
