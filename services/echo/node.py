"""Echo node: relays a camera's frames to its ``echo`` key, header untouched.

The smallest real pipeline stage: it decodes each frame (so bad payloads are counted),
re-encodes it and publishes it, which makes two process hops observable end to end.
"""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field

from protocol.keys import KeyName
from protocol.sensors import Image
from services.bus.pubsub import Role
from services.runtime.kind import NodeKind
from services.runtime.node import Node


class Params(BaseModel):
    """Which camera to relay, and how many frames its input may hold."""

    model_config = ConfigDict(extra="forbid")

    camera: KeyName = "cam0"
    depth: int = Field(default=1, ge=1, le=1000,
                       description="frames queued while busy; 1 = latest-wins, more rides out stalls")


def run(node: Node, params: Params) -> None:
    frames = node.inbox(node.keys.image(params.camera), Image, Role.FRAME, depth=params.depth)
    out = node.publisher(node.keys.echo(params.camera), Image, Role.FRAME)
    for image in node.inputs(frames):
        out.put(image)


KIND = NodeKind(name="echo", summary="relays a camera's frames to its echo key",
                params=Params, run=run, inputs=("{camera}/image",), outputs=("{camera}/echo",))
