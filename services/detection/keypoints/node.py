"""Keypoints node: keypoints and descriptors of one camera's frames (``services.detection.keypoints.detector``).

Each frame on ``<camera>/image`` yields one ``protocol.detections.Keypoints`` on
``<camera>/keypoints`` with the frame's header unchanged, zero rows when nothing was found.
``method`` picks the detector (``orb``, ``sift``, ``akaze``, ``harris``, ``shi_tomasi``),
``descriptor`` its own descriptors (``native``) or TEBLID's; at most ``max_count`` keypoints are
kept, spread over the frame by ``grid`` bucketing (cells of ``cell_px``), ``anms`` or not at
all (``none``).

Frames may be mono8, mono16 (scaled to 8 bits by 1/257), bgr8 or bgra8 (made grey). A frame
with a side under ``MIN_SIDE_PX`` gets an empty Keypoints and is reported as skipped
(``services.runtime.frame_detection``). One frame may wait while
another is searched (``depth``).
"""

from __future__ import annotations

from typing import Annotated

import numpy as np
from pydantic import Field

from protocol.detections import Keypoints
from protocol.keys import KeyName
from protocol.message import Header
from services.bus.pubsub import Role
from services.detection.grey import as_grey8
from services.detection.keypoints.detector import EDGE_PX, KeypointDetector, KeypointParams
from services.detection.keypoints.detector import Keypoints as FoundKeypoints
from services.runtime.frame_detection import UnusableFrame, detect_frames
from services.runtime.kind import NodeKind
from services.runtime.node import Node, NodeError
from services.runtime.params import Flat, NodeParams

MIN_SIDE_PX = 2 * EDGE_PX + 1
"""The shortest frame side searched: the smallest that leaves a pixel inside ORB's border on both sides."""


class Params(NodeParams):
    """Which camera, which detector and descriptor, how many keypoints, their spread and thresholds."""

    camera: KeyName = "cam0"
    keypoints: Annotated[KeypointParams, Flat()] = KeypointParams()
    depth: int = Field(default=2, ge=1, le=1000, description="frames queued while busy")


def frame_keypoints(keypoints: KeypointDetector, data: np.ndarray) -> FoundKeypoints:
    """The keypoints of one frame's pixels: (H, W) uint8 or uint16, or (H, W, 3|4) uint8 BGR(A)
    (UnusableFrame for a frame with a side under ``MIN_SIDE_PX``)."""
    if min(data.shape[:2]) < MIN_SIDE_PX:
        height, width = data.shape[:2]
        raise UnusableFrame(f"a {width}x{height} frame is too small for keypoints (sides of {MIN_SIDE_PX} px at least)")
    return keypoints.detect(as_grey8(data))


def as_message(header: Header, found: FoundKeypoints) -> Keypoints:
    """``found`` in the frame with ``header`` as the message that carries it."""
    return Keypoints(header=header, method=found.method, descriptor_type=found.descriptor_type, points=found.points,
                     sizes=found.sizes, angles=found.angles, responses=found.responses, descriptors=found.descriptors)


def run(node: Node, params: Params) -> None:
    try:
        keypoints = KeypointDetector(params.keypoints)
    except ValueError as exc:
        raise NodeError(str(exc)) from exc
    out = node.publisher(node.keys.keypoints(params.camera), Keypoints, Role.RESULT)
    for image, found in detect_frames(node, params.camera, params.depth,
                                      lambda data: frame_keypoints(keypoints, data), keypoints.empty):
        out.put(as_message(image.header, found))


def _check(params: Params) -> None:
    KeypointDetector(params.keypoints)


KIND = NodeKind(name="keypoints", summary="keypoints and descriptors (ORB, SIFT, AKAZE, Harris, Shi-Tomasi) of a "
                "camera's frames", params=Params, run=run, inputs=("{camera}/image",),
                outputs=("{camera}/keypoints",), check=_check)
