"""Foxglove node: the rig served live over Foxglove's WebSocket protocol (``foxglove.websocket.v1``), and/or
written as a Foxglove MCAP file while it runs.

It subscribes to the streams the Rerun viewer node draws (``services.viewer.node.subscriptions``:
images and overlays latest-wins, calibrations, detections, poses, bodies, points and maps in order,
node health) and to the rig's static data (``protocol.keys.Keys.latched``: static transforms, image
targets), which it also asks for when it starts (``services.bus.latched``), so a node joining a running
rig still draws the targets' outlines and the cameras' placement. It turns each message into Foxglove's
well-known messages with ``services.viewer.foxglove_messages`` (the topics and schemas ``artrack export
--format foxglove`` writes) and logs them on typed channels, one per topic, made when its first message arrives. Open
Foxglove, "Open connection", ``ws://127.0.0.1:8765``.

Served (``serve``, the default), images are limited to ``image_hz`` per topic by the Rerun viewer's
``RateGate`` (slots of the frames' own stamps, repeats held back); every other message goes out as it
arrives. The server binds 127.0.0.1 by default (this machine only: it has no authentication); ``bind``
0.0.0.0 serves every interface. It is stopped when the node stops.

The server keeps what shows the static data (``/tf_static``, ``/<camera>/target_outlines``) and sends it
again on its channel whenever a client subscribes to it (``Outputs.on_subscribe``): a Foxglove app that
connects after the rig started still gets the cameras' placement and the targets' outlines.

Written (``mcap``), every message the node takes goes into the file, images included: every frame
in a lossless run, the newest ``image_depth`` (latest-wins, as served) in a real-time one. The file
is ``foxglove.open_mcap``'s: protobuf channels and schemas as the server's, zstd chunks of 1 MiB, a
summary with indexes and statistics. The server and the file are two Foxglove contexts, each with
its own channels, so the file never sees the server's gate. A message's log time is when the node
took it (wall clock, never going back), so the file is in log-time order; its publish time is the
same (the artrack stamp is each message's ``timestamp``). An existing file is refused unless
``force``. On SIGINT/SIGTERM or once its upstream nodes have ended (a finite run), what the inboxes
still hold is written and the file finished; a node killed outright leaves it without its summary.
"""

from __future__ import annotations

import threading
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

import foxglove
import foxglove.channels
from foxglove.mcap import MCAPCompression, MCAPWriteOptions
from foxglove.messages import CompressedImage, RawImage
from foxglove.websocket import ChannelView, Client, ServerListener
from pydantic import BaseModel, ConfigDict, Field, model_validator

from protocol.keys import Keys
from protocol.message import Message
from protocol.spatial import StaticTransforms
from protocol.targets import ImageTargets
from services.bus.latched import ask_latched
from services.bus.pubsub import Inbox, Role
from services.runtime.kind import NodeKind, SinkRole
from services.runtime.node import Node, NodeError
from services.runtime.outputs import check_output
from services.viewer import node as viewer_node
from services.viewer.foxglove_export import CHUNK_BYTES
from services.viewer.foxglove_messages import FoxgloveConversion, FoxgloveMessage, FoxgloveOptions
from services.viewer.images import RateGate


class Params(BaseModel):
    """Where to serve and/or what file to write, and how much of the images to serve."""

    model_config = ConfigDict(extra="forbid")

    serve: bool = Field(default=True, description="serve the rig over Foxglove's WebSocket protocol")
    port: int = Field(default=8765, ge=0, le=65535, description="the WebSocket server's port (0: any free port)")
    bind: str = Field(default="127.0.0.1", description="the server's address; 0.0.0.0 = every interface")
    mcap: Path | None = Field(default=None, description="the MCAP file to write what the node converts "
                                                        "to (every image: image_hz limits the server only)")
    force: bool = Field(default=False, description="overwrite the mcap file if it exists")
    image_hz: float = Field(default=10.0, ge=0, description="at most this many images per camera per second "
                                                            "served; 0 = every frame that arrives")
    image_depth: int = Field(default=4, ge=1, le=64, description="newest frames held for all cameras together")
    compressed: bool = Field(default=False, description="send images as JPEG (mono16 as PNG), not raw pixels")
    jpeg_quality: int = Field(default=90, ge=1, le=100, description="JPEG quality of compressed images")

    @model_validator(mode="after")
    def _somewhere(self) -> Params:
        if self.mcap is None and not self.serve:
            raise ValueError("give `mcap` (a file to write), `serve`, or both")
        return self


class Channels:
    """A Foxglove context's typed channels, one per topic, made when its first message comes."""

    def __init__(self, context: foxglove.Context):
        self.context = context
        self._channels: dict[str, Any] = {}

    def log(self, topic: str, shown: FoxgloveMessage, log_ns: int | None = None) -> None:
        """Log ``shown`` on ``topic`` at ``log_ns`` (None: now)."""
        channel = self._channels.get(topic)
        if channel is None:
            kind = getattr(foxglove.channels, f"{type(shown).__name__}Channel")
            channel = self._channels[topic] = kind(topic, context=self.context)
        channel.log(shown, log_time=log_ns)


STATIC = (StaticTransforms, ImageTargets)
"""Messages that describe what does not change while the rig runs: sent again to each client that subscribes."""


class Outputs(ServerListener):
    """The node's server and/or file (``params.serve``, ``params.mcap``): each message converted once, sent to the
    server with images gated to ``image_hz`` per topic, written to the file whole; what shows static data is sent
    again to a client that subscribes to its topic. ``sent`` and ``written`` count the Foxglove messages each
    took. NodeError when the server cannot bind or the file cannot be opened."""

    def __init__(self, params: Params, name: str):
        self.convert = FoxgloveConversion(FoxgloveOptions(compressed=params.compressed,
                                                          jpeg_quality=params.jpeg_quality))
        self.sent = 0
        self.written = 0
        self.server: foxglove.WebSocketServer | None = None
        self._writer: foxglove.mcap.MCAPWriter | None = None
        self._gate = RateGate(params.image_hz)
        self._served: Channels | None = None
        self._filed: Channels | None = None
        self._last_ns = 0
        self._static: defaultdict[str, list[FoxgloveMessage]] = defaultdict(list)
        self._static_lock = threading.Lock()
        if params.serve:
            self._served = Channels(foxglove.Context())
            try:
                self.server = foxglove.start_server(name=name, host=params.bind, port=params.port,
                                                    context=self._served.context, server_listener=self)
            except RuntimeError as exc:  # foxglove's FoxgloveError: the port is taken, the address is not this host's
                raise NodeError(f"cannot serve Foxglove on {params.bind}:{params.port}: {exc}") from exc
        if params.mcap is not None:
            self._filed = Channels(foxglove.Context())
            try:
                self._writer = foxglove.open_mcap(params.mcap, allow_overwrite=params.force,
                                                  context=self._filed.context, writer_options=MCAPWriteOptions(
                                                      compression=MCAPCompression.Zstd, chunk_size=CHUNK_BYTES))
            except (RuntimeError, OSError) as exc:  # FoxgloveError: the file exists, its folder is missing
                self.close()
                raise NodeError(f"cannot write {params.mcap}: {exc}") from exc

    def log(self, message: Message) -> None:
        """Send what shows ``message`` (images over the rate held back) and write all of it."""
        log_ns = self._last_ns = max(self._last_ns, time.time_ns())
        for topic, shown in self.convert(message):
            if self._filed is not None:
                self._filed.log(topic, shown, log_ns)
                self.written += 1
            if self._served is None:
                continue
            if isinstance(shown, RawImage | CompressedImage) and not self._gate.admit(topic, message.header.stamp_ns):
                continue
            if isinstance(message, STATIC):
                with self._static_lock:
                    self._static[topic].append(shown)
            self._served.log(topic, shown)
            self.sent += 1

    def on_subscribe(self, client: Client, channel: ChannelView) -> None:
        """Send the static data shown on ``channel`` again (every subscriber of the channel gets it: the same data)."""
        with self._static_lock:
            again = list(self._static.get(channel.topic, ()))
        if self._served is not None:
            for shown in again:
                self._served.log(channel.topic, shown)
                self.sent += 1

    def close(self) -> None:
        """Finish the file (summary and indexes) and stop the server."""
        if self._writer is not None:
            self._writer.close()
            self._writer = None
        if self.server is not None:
            self.server.stop()
            self.server = None


def subscriptions(keys: Keys) -> list[tuple[str, Role]]:
    """``(key expression, role)`` of every stream the node subscribes to: the Rerun viewer's and the static data."""
    return [*viewer_node.subscriptions(keys), *((key, Role.RESULT) for key in keys.latched())]


def run(node: Node, params: Params) -> None:
    inboxes: list[Inbox[Message]] = [node.inbox(key, None, role, params.image_depth if role is Role.FRAME else None)
                                     for key, role in subscriptions(node.keys)]
    latched = node.keys.latched()
    for inbox in inboxes:
        if inbox.key in latched:
            ask_latched(node.session, inbox.key, latched, inbox.offer)
    outputs = Outputs(params, f"artrack {node.keys.prefix}")
    try:
        if outputs.server is not None:
            node.log.info("serving %s to Foxglove on ws://%s:%d", node.keys.prefix, params.bind, outputs.server.port)
        if params.mcap is not None:
            node.log.info("writing %s for Foxglove to %s", node.keys.prefix, params.mcap)
        for message in node.inputs(*inboxes):
            outputs.log(message)
        for inbox in inboxes:  # what arrived before the stop is sent too
            while (received := inbox.take()) is not None:
                outputs.log(received.message)
    finally:
        outputs.close()
    done = [f"sent {outputs.sent} messages to Foxglove"] if params.serve else []
    if params.mcap is not None:
        done.append(f"wrote {outputs.written} messages to {params.mcap}")
    node.log.info("%s", ", ".join(done))


def _inputs(params: Params) -> tuple[str, ...]:
    rig = Keys()
    return (*viewer_node.KIND.keys(params)[0], *(key.removeprefix(f"{rig.prefix}/") for key in rig.latched()))


def _check(params: Params) -> None:
    if params.mcap is not None:
        check_output(params.mcap, params.force)


KIND = NodeKind(name="foxglove", summary="serves the rig live to Foxglove over its WebSocket protocol and/or "
                                         "writes it as a Foxglove MCAP file",
                params=Params, run=run, inputs=_inputs, outputs=(), check=_check,
                sink=SinkRole(files=lambda params: () if params.mcap is None else
                              (("foxglove recording", params.mcap),)))
