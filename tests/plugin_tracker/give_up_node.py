"""Give-up node: takes a camera's first frame, then stops with a NodeError saying why it cannot go on.

It stands for a node that learns only from its data that it cannot do its job (a calibration file
for another frame size, on a live camera whose size no check before start can know).
"""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict

from protocol.keys import KeyName
from protocol.sensors import Image
from services.bus.pubsub import Role
from services.runtime.kind import NodeKind
from services.runtime.node import Node, NodeError


class Params(BaseModel):
    model_config = ConfigDict(extra="forbid")

    camera: KeyName = "cam0"


def run(node: Node, params: Params) -> None:
    frames = node.inbox(node.keys.image(params.camera), Image, Role.FRAME)
    for image in node.inputs(frames):
        raise NodeError(f"{params.camera} sends {image.width}x{image.height} frames, which this node cannot use")


KIND = NodeKind(name="give_up", summary="stops at a camera's first frame, saying it cannot use it", params=Params,
                run=run, inputs=("{camera}/image",), outputs=())
