"""The pipelines ``artrack run`` knows: which nodes each runs per camera, and its options.

Kept apart from ``jobs`` (which imports the capture and recorder code) so the command line
can list pipelines without loading OpenCV.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

NodeSet = dict[str, tuple[str, dict[str, Any]]]
"""``{node name: (kind, params)}``."""


@dataclass(frozen=True)
class Pipeline:
    """What a pipeline runs per camera, and which job options it takes (``artrack run --OPTION``)."""

    summary: str
    options: tuple[str, ...]
    nodes: Callable[[list[str], dict[str, Any]], NodeSet]


def _marker_nodes(cameras: list[str], options: dict[str, Any]) -> NodeSet:
    """One marker node per camera, detecting and estimating in one process (two hops from frame to pose)."""
    return {f"marker-{camera}": ("marker_pose", {"camera": camera, **options}) for camera in cameras}


PIPELINES: dict[str, Pipeline] = {
    "capture": Pipeline("the source alone", (), lambda cameras, options: {}),
    "echo": Pipeline("relays each camera's frames to its echo key", (),
                     lambda cameras, options: {f"echo-{c}": ("echo", {"camera": c}) for c in cameras}),
    "marker": Pipeline("ArUco/AprilTag detection -> marker and board poses per camera",
                       ("dictionary", "marker_length", "board", "method", "overlay", "depth"), _marker_nodes),
}
