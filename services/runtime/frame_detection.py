"""What every per-frame detector node (blobs, keypoints) does with its camera's frames.

``detect_frames`` takes the newest frames of ``<camera>/image`` (latest-wins, ``depth`` waiting
while one is searched) and gives each with what the node's detector found in its pixels. A frame
the detector cannot work on (it raises ``UnusableFrame``, whose message says why) gets the node's
empty result instead, and is counted as a skipped ``unusable_frame`` input, reported on the node's
errors key and in its log (at most once a second, ``Node.report``).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import TypeVar

import numpy as np

from protocol.sensors import Image
from services.bus.pubsub import Role
from services.runtime.node import Node

__all__ = ["UnusableFrame", "detect_frames"]

Found = TypeVar("Found")


class UnusableFrame(ValueError):
    """A frame the detector cannot work on; the message says why."""


def detect_frames(node: Node, camera: str, depth: int, detect: Callable[[np.ndarray], Found],
                  empty: Callable[[], Found]) -> Iterator[tuple[Image, Found]]:
    """``(frame, found)`` for each frame of ``camera`` the node takes: ``detect(frame.data)``, or ``empty()``
    for a frame ``detect`` refuses with ``UnusableFrame``."""
    key = node.keys.image(camera)
    for image in node.inputs(node.inbox(key, Image, Role.FRAME, depth=depth)):
        try:
            found = detect(image.data)
        except UnusableFrame as exc:
            node.report("unusable_frame", str(exc), key)
            found = empty()
        yield image, found
