"""The node kinds artrack can start: name -> the module holding its ``Params`` and ``run``.

A node module defines ``Params`` (a pydantic model of its settings, extra keys refused)
and ``run(node, params)``. Modules are imported only when a kind is used.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from types import ModuleType
from typing import Any

from pydantic import BaseModel


@dataclass(frozen=True)
class NodeKind:
    name: str
    module: str
    summary: str

    def load(self) -> ModuleType:
        return importlib.import_module(self.module)

    def params(self, values: dict[str, Any]) -> BaseModel:
        """Validated parameters (raises pydantic's ValidationError naming the field)."""
        return self.load().Params.model_validate(values)


KINDS: dict[str, NodeKind] = {
    kind.name: kind
    for kind in (
        NodeKind("capture", "services.capture.node", "publishes camera frames + calibration from a source"),
        NodeKind("echo", "services.echo.node", "relays a camera's frames to its echo key"),
        NodeKind("markers", "services.detection.node", "detects ArUco/AprilTag markers in a camera's frames"),
        NodeKind("marker_pose", "services.estimation.node",
                 "marker and board poses from a camera's frames (or a markers node's detections)"),
        NodeKind("recorder", "services.recorder.record_node", "records the rig's keys to MCAP files"),
        NodeKind("replay", "services.recorder.replay_node", "publishes a recording back onto its keys"),
        NodeKind("viewer", "services.viewer.node", "logs the rig to Rerun: an .rrd file and/or a gRPC server"),
    )
}


def kind(name: str) -> NodeKind:
    """The node kind called ``name``; ValueError listing the known kinds otherwise."""
    if name not in KINDS:
        raise ValueError(f"unknown node kind {name!r} (known: {', '.join(sorted(KINDS))})")
    return KINDS[name]
