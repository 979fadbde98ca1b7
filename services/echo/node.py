"""Echo node: relays a camera's frames to its ``echo`` key, header untouched.

The smallest real pipeline stage: it decodes each frame (so bad payloads are counted),
re-encodes it and publishes it, which makes two process hops observable end to end.
"""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict

from protocol.sensors import Image
from services.runtime.node import Node
from services.runtime.pubsub import Role


class Params(BaseModel):
    """Which camera to relay."""

    model_config = ConfigDict(extra="forbid")

    camera: str = "cam0"


def run(node: Node, params: Params) -> None:
    frames = node.inbox(node.keys.image(params.camera), Image, Role.FRAME)
    out = node.publisher(node.keys.echo(params.camera), Image, Role.FRAME)
    for image in node.inputs(frames):
        out.put(image)
