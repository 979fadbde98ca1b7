"""Markers node: finds ArUco / AprilTag markers in one camera's frames and publishes them.

Each frame on ``<camera>/image`` yields one ``MarkerDetections`` on ``<camera>/markers``
with the frame's header unchanged, zero rows when nothing was found. One frame may wait
while another is searched (``depth`` 2), so a stall of the node or a late frame that comes
in a burst with the next costs latency, not a frame; a frame arriving when ``depth`` wait
already replaces the oldest, which is counted as dropped (latest wins). The algorithm and
the meaning of each setting are in ``services.detection.markers.detector``.
"""

from __future__ import annotations

from typing import Annotated, ClassVar

from pydantic import Field

from protocol.detections import MarkerDetections
from protocol.keys import KeyName
from protocol.message import Header
from protocol.sensors import Image
from services.bus.pubsub import Role
from services.detection.markers.detector import MarkerFound
from services.detection.markers.settings import DetectorSettings
from services.runtime.kind import NodeKind
from services.runtime.node import Node, NodeError
from services.runtime.params import Flat, NodeParams


class Params(NodeParams):
    """Which camera to watch, which markers to look for, and how; the detector's tuning (side
    lengths, refinement, ``parameters`` thresholds) may change while it runs."""

    RELOADABLE: ClassVar[frozenset[str]] = DetectorSettings.TUNING

    detection: Annotated[DetectorSettings, Flat()] = DetectorSettings()
    camera: KeyName = "cam0"
    depth: int = Field(default=2, ge=1, le=1000,
                       description="frames queued while busy; 1 = always the newest only, more rides out stalls")


def run(node: Node, params: Params) -> None:
    try:
        markers = params.detection.detector()
    except ValueError as exc:
        raise NodeError(str(exc)) from exc
    current = {"detector": markers}
    node.configurable(params, lambda new: current.update(detector=new.detection.detector()))
    frames = node.inbox(node.keys.image(params.camera), Image, Role.FRAME, depth=params.depth)
    out = node.publisher(node.keys.markers(params.camera), MarkerDetections, Role.RESULT)
    for image in node.inputs(frames):
        out.put(as_message(image.header, params.detection.dictionary, current["detector"].detect(image.data)))


def as_message(header: Header, dictionary: str, found: MarkerFound) -> MarkerDetections:
    """``found`` in an image with ``header`` as the message that carries it.

    Not validated again: ``MarkerDetector.detect`` gives native int32 / float32 arrays of the message's
    shapes, aligned (tests/unit/test_tracker_messages.py holds the two against each other), and the
    array checks would otherwise be paid on every frame for nothing.
    """
    return MarkerDetections.model_construct(header=header, dictionary=dictionary, ids=found.ids,
                                            corners=found.corners, quality=found.quality, side_m=found.side_m)


def _check(params: Params) -> None:
    params.detection.detector()


KIND = NodeKind(name="markers", summary="detects ArUco/AprilTag markers in a camera's frames",
                params=Params, run=run, inputs=("{camera}/image",), outputs=("{camera}/markers",), check=_check)
