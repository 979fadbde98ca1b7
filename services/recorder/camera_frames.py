"""The camera images of a recording, grouped into rig frames, and the cameras' recorded calibration.

Images are the ``<prefix>/<camera>/image`` messages (``Image``), calibrations the
``<prefix>/<camera>/camera_info`` ones (``CameraInfo``); the camera's name is the key's segment
before the stream. A rig frame is the set of images that share a capture stamp
(``header.stamp_ns``), as a multi-camera capture stamps the images of one trigger. The file is
read front to back with the damage-tolerant reader; a damaged file yields its intact part.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Generic, TypeVar

import numpy as np

from protocol.codec import DecodeError, decode
from protocol.sensors import CameraInfo, Image
from services.recorder.reading import Damage, Scan

__all__ = ["CameraFrames", "camera_frames"]

T = TypeVar("T")


@dataclass
class CameraFrames(Generic[T]):
    """What ``camera_frames`` found: ``frames``: capture stamp (ns) -> camera -> the value computed from
    that camera's image (in stamp order); ``infos``: camera -> its last CameraInfo; ``undecodable``:
    image or camera_info payloads that did not decode; ``damage``: None for an intact file."""

    frames: dict[int, dict[str, T]] = field(default_factory=dict)
    infos: dict[str, CameraInfo] = field(default_factory=dict)
    undecodable: int = 0
    damage: Damage | None = None

    @property
    def cameras(self) -> list[str]:
        """Every camera with an image, sorted by name."""
        return sorted({camera for frame in self.frames.values() for camera in frame})


def camera_frames(path: Path | str, per_image: Callable[[np.ndarray], T]) -> CameraFrames[T]:
    """Every camera image of the recording at ``path`` reduced by ``per_image`` ((H, W[, C]) pixels in,
    anything out: images are not kept), grouped by capture stamp; NotMcap for a file that is not MCAP."""
    scan = Scan(path)
    found: CameraFrames[T] = CameraFrames()
    for recorded in scan.messages():
        prefix, _, stream = recorded.channel.topic.rpartition("/")
        if stream not in ("image", "camera_info") or not prefix:
            continue
        camera = prefix.rpartition("/")[2]
        try:
            message = decode(recorded.message.data)
        except DecodeError:
            found.undecodable += 1
            continue
        if isinstance(message, Image):
            found.frames.setdefault(message.header.stamp_ns, {})[camera] = per_image(message.data)
        elif isinstance(message, CameraInfo):
            found.infos[camera] = message
    found.frames = dict(sorted(found.frames.items()))
    found.damage = scan.damage
    return found
