"""Viewer node: the rig's streams logged to Rerun, headless (an .rrd file and/or a gRPC server).

It subscribes to every stream of the rig that the viewer draws, one inbox per stream kind,
and logs each message on the node's own thread (Zenoh's callbacks only copy bytes into the
inboxes), so a slow viewer never holds up the pipeline:

* ``<prefix>/*/image``: role FRAME, latest-wins. One inbox serves every camera and holds the
  newest ``image_depth`` frames of all of them together (keep it at least the number of
  cameras); frames it replaces are counted as dropped in the node's stats.
* ``<prefix>/*/overlay``: the marker node's AR overlays (frames with the tracked targets
  drawn), role FRAME, in an inbox of their own of the same depth, so overlays never push
  camera frames out. Their frame id is ``<camera>/overlay``: each is drawn as the image of a
  camera of that name (``world/<camera>/overlay/image``, a 2D view of its own; no
  calibration, so not in the 3D view).
* ``*/camera_info``, ``*/markers``, ``*/blobs``, ``*/keypoints``, ``*/truth``, a SLAM node's
  ``*/keyframes``, ``*/map`` and ``*/timings``, ``pose/**``, ``bodies``, ``map``: role RESULT, in
  order, never dropped silently.
* ``node/*/stats``, ``node/*/errors``: role STATUS (node health, this node's included).

Images are further limited to ``image_hz`` per camera (10 by default; 0 = every frame that
arrives) and can be stored as JPEG (``jpeg_quality``). On SIGINT/SIGTERM what the inboxes
still hold is logged, then the file is flushed and closed. An ``rrd`` that exists is refused before the
node starts unless ``force``. Layout and timelines:
``services.viewer.layout``; sinks and the gRPC bind address (127.0.0.1 by default, unlike
``rr.serve_grpc``'s 0.0.0.0): ``services.viewer.recording``.
"""

from __future__ import annotations

from pathlib import Path

from pydantic import Field, model_validator

from protocol.keys import Keys
from protocol.message import Message
from services.bus.pubsub import Inbox, Role
from services.runtime.kind import NodeKind, SinkRole
from services.runtime.node import Node
from services.runtime.outputs import check_output
from services.viewer.recording import Serve, ViewLog, open_recording
from services.viewer.scene import Scene, ViewOptions

CAMERA_STREAMS = {"image": Role.FRAME, "overlay": Role.FRAME, "camera_info": Role.RESULT, "markers": Role.RESULT,
                  "blobs": Role.RESULT, "keypoints": Role.RESULT, "truth": Role.RESULT, "keyframes": Role.RESULT,
                  "map": Role.RESULT, "timings": Role.RESULT}
"""The per-camera streams of ``protocol.keys`` that the viewer draws, with their roles."""


class Params(ViewOptions):
    """Where to log (a file, a server, or both), plus how to draw (``ViewOptions``)."""

    rrd: Path | None = Field(default=None, description="the .rrd file to write")
    force: bool = Field(default=False, description="overwrite the rrd file if it exists")
    serve: bool = Field(default=False, description="serve the recording over gRPC for viewers to connect to")
    port: int = Field(default=9876, ge=1, le=65535, description="the gRPC server's port")
    bind: str = Field(default="127.0.0.1", description="the gRPC server's address; 0.0.0.0 = every interface")
    memory_limit: str = Field(default="1GiB", description="what the server keeps for late viewers, e.g. 512MiB")
    image_hz: float = Field(default=10.0, ge=0, description="at most this many images per camera per second; "
                                                            "0 = every frame that arrives")
    image_depth: int = Field(default=4, ge=1, le=64, description="newest frames held for all cameras together")

    @model_validator(mode="after")
    def _somewhere(self) -> Params:
        if self.rrd is None and not self.serve:
            raise ValueError("give `rrd` (a file to write), `serve`, or both")
        return self

    def server(self) -> Serve | None:
        return Serve(self.port, self.bind, self.memory_limit) if self.serve else None


def subscriptions(keys: Keys) -> list[tuple[str, Role]]:
    """``(key expression, role)`` of every stream the viewer subscribes to."""
    return [
        *((keys.every_camera(stream), role) for stream, role in CAMERA_STREAMS.items()),
        (keys.poses(), Role.RESULT), (keys.bodies(), Role.RESULT), (keys.map(), Role.RESULT),
        (keys.points(), Role.RESULT), (keys.every_node("stats"), Role.STATUS), (keys.every_node("errors"), Role.STATUS),
    ]


def run(node: Node, params: Params) -> None:
    inboxes: list[Inbox[Message]] = [node.inbox(key, None, role, params.image_depth if role is Role.FRAME else None)
               for key, role in subscriptions(node.keys)]
    serve = params.server()
    recording = open_recording(f"{node.keys.prefix} ({node.name})", out=params.rrd, serve=serve)
    with ViewLog(recording, Scene(params)) as view:
        node.log.info("viewing %s: %s%s", node.keys.prefix, params.rrd or "no file",
                      f", serving {serve.url}" if serve else "")
        for message in node.inputs(*inboxes):
            view.log(message)
        for inbox in inboxes:  # what arrived before the stop is logged too
            while (received := inbox.take()) is not None:
                view.log(received.message)
        node.log.info("logged %d rows", view.rows)


def _inputs(params: Params) -> tuple[str, ...]:
    return (*(f"*/{stream}" for stream in CAMERA_STREAMS), "pose/**", "bodies", "map", "points", "node/*/stats",
            "node/*/errors")


def _check(params: Params) -> None:
    if params.rrd is not None:
        check_output(params.rrd, params.force)


KIND = NodeKind(name="viewer", summary="logs the rig to Rerun: an .rrd file and/or a gRPC server",
                params=Params, run=run, inputs=_inputs, outputs=(), check=_check,
                sink=SinkRole(files=lambda params: () if params.rrd is None else (("rerun file", params.rrd),)))
