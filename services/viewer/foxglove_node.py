"""Foxglove node: the rig served live over Foxglove's WebSocket protocol (``foxglove.websocket.v1``).

It subscribes to the streams the Rerun viewer node draws (``services.viewer.node.subscriptions``:
images and overlays latest-wins, calibrations, detections, poses, bodies, points and maps in order,
node health), turns each message into Foxglove's well-known messages with
``services.viewer.foxglove_messages`` (the topics and schemas ``artrack export --format foxglove``
writes) and logs them on the server's channels, one typed channel per topic, made when its first
message arrives. Open Foxglove, "Open connection", ``ws://127.0.0.1:8765``.

Images are limited to ``image_hz`` per topic by the Rerun viewer's ``RateGate`` (slots of the frames'
own stamps, repeats held back); every other message goes out as it arrives. The server binds
127.0.0.1 by default (this machine only: it has no authentication); ``bind`` 0.0.0.0 serves every
interface. It is stopped when the node stops.
"""

from __future__ import annotations

from typing import Any

import foxglove
import foxglove.channels
from foxglove.messages import CompressedImage, RawImage
from pydantic import BaseModel, ConfigDict, Field

from protocol.message import Message
from services.bus.pubsub import Inbox, Role
from services.runtime.kind import NodeKind
from services.runtime.node import Node, NodeError
from services.viewer import node as viewer_node
from services.viewer.foxglove_messages import FoxgloveOptions, to_foxglove
from services.viewer.images import RateGate


class Params(BaseModel):
    """Where to serve, and how much of the images."""

    model_config = ConfigDict(extra="forbid")

    port: int = Field(default=8765, ge=0, le=65535, description="the WebSocket server's port (0: any free port)")
    bind: str = Field(default="127.0.0.1", description="the server's address; 0.0.0.0 = every interface")
    image_hz: float = Field(default=10.0, ge=0, description="at most this many images per camera per second; "
                                                            "0 = every frame that arrives")
    image_depth: int = Field(default=4, ge=1, le=64, description="newest frames held for all cameras together")
    compressed: bool = Field(default=False, description="send images as JPEG (mono16 as PNG), not raw pixels")
    jpeg_quality: int = Field(default=90, ge=1, le=100, description="JPEG quality of compressed images")


class Server:
    """A Foxglove WebSocket server with a channel per topic, images gated to ``image_hz`` per topic; ``sent``
    counts the messages logged on its channels. NodeError when the server cannot bind."""

    def __init__(self, params: Params, name: str):
        self.context = foxglove.Context()
        try:
            self.server = foxglove.start_server(name=name, host=params.bind, port=params.port, context=self.context)
        except RuntimeError as exc:  # foxglove's FoxgloveError: the port is taken, the address is not this host's
            raise NodeError(f"cannot serve Foxglove on {params.bind}:{params.port}: {exc}") from exc
        self.options = FoxgloveOptions(compressed=params.compressed, jpeg_quality=params.jpeg_quality)
        self.sent = 0
        self._gate = RateGate(params.image_hz)
        self._channels: dict[str, Any] = {}

    def log(self, message: Message) -> None:
        """Send what shows ``message`` (images over the rate held back)."""
        for topic, shown in to_foxglove(message, self.options):
            if isinstance(shown, RawImage | CompressedImage) and not self._gate.admit(topic, message.header.stamp_ns):
                continue
            channel = self._channels.get(topic)
            if channel is None:
                kind = getattr(foxglove.channels, f"{type(shown).__name__}Channel")
                channel = self._channels[topic] = kind(topic, context=self.context)
            channel.log(shown)
            self.sent += 1

    def stop(self) -> None:
        self.server.stop()


def run(node: Node, params: Params) -> None:
    inboxes: list[Inbox[Message]] = [node.inbox(key, None, role, params.image_depth if role is Role.FRAME else None)
                                     for key, role in viewer_node.subscriptions(node.keys)]
    server = Server(params, f"artrack {node.keys.prefix}")
    try:
        node.log.info("serving %s to Foxglove on ws://%s:%d", node.keys.prefix, params.bind, server.server.port)
        for message in node.inputs(*inboxes):
            server.log(message)
        for inbox in inboxes:  # what arrived before the stop is sent too
            while (received := inbox.take()) is not None:
                server.log(received.message)
        node.log.info("sent %d messages", server.sent)
    finally:
        server.stop()


KIND = NodeKind(name="foxglove", summary="serves the rig live to Foxglove over its WebSocket protocol",
                params=Params, run=run, inputs=viewer_node.KIND.inputs, outputs=())
