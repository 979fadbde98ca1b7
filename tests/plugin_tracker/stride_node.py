"""Stride node: relays every ``every``-th frame of a camera to its ``stride`` key."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field

from protocol.keys import KeyName
from protocol.sensors import Image
from services.bus.pubsub import Role
from services.runtime.kind import NodeKind
from services.runtime.node import Node


class Params(BaseModel):
    model_config = ConfigDict(extra="forbid")

    camera: KeyName = "cam0"
    every: int = Field(default=2, ge=1, description="relay one frame in this many (by sequence number)")


def run(node: Node, params: Params) -> None:
    frames = node.inbox(node.keys.image(params.camera), Image, Role.FRAME, depth=1000)
    out = node.publisher(node.keys.camera(params.camera, "stride"), Image, Role.RESULT)
    for image in node.inputs(frames):
        if image.header.seq % params.every == 0:
            out.put(image)


KIND = NodeKind(name="stride", summary="relays every n-th frame of a camera", params=Params, run=run,
                inputs=("{camera}/image",), outputs=("{camera}/stride",))
