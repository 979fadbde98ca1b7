"""Camera frames as Rerun images, and the rate limit that keeps images cheap to view.

Pixels are handed to Rerun as they travel: mono8 and mono16 as colour model ``L``, bgr8 as
``BGR``, bgra8 as ``BGRA`` (the viewer swaps channels when it draws; nothing is converted
here). With a JPEG quality, 8-bit frames are encoded with ``cv2.imencode`` and logged as an
``EncodedImage`` (``image/jpeg``): a frame takes a fraction of its raw size in the viewer,
for a little more time to log it (``tests/bench/viewer.py``, figures in docs/benchmarks.md).
bgra8 loses its alpha, and mono16, which JPEG cannot hold, stays raw.
"""

from __future__ import annotations

from typing import Literal

import cv2
import rerun as rr

from protocol.sensors import Image

_COLOR_MODELS: dict[str, Literal["L", "BGR", "BGRA"]] = {"mono8": "L", "mono16": "L", "bgr8": "BGR", "bgra8": "BGRA"}


def image_archetype(image: Image, jpeg_quality: int = 0) -> rr.Image | rr.EncodedImage:
    """``image`` as raw pixels (``jpeg_quality`` 0) or as a JPEG of that quality (1-100)."""
    if not jpeg_quality or image.encoding == "mono16":
        return rr.Image(image.data, color_model=_COLOR_MODELS[image.encoding])
    pixels = cv2.cvtColor(image.data, cv2.COLOR_BGRA2BGR) if image.encoding == "bgra8" else image.data
    ok, jpeg = cv2.imencode(".jpg", pixels, [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality])
    if not ok:
        raise ValueError(f"OpenCV could not JPEG-encode a {image.width}x{image.height} {image.encoding} frame")
    return rr.EncodedImage(contents=jpeg.tobytes(), media_type="image/jpeg")


class RateGate:
    """Lets through at most one frame per entity in each ``1/hz`` slot of the frames' own stamps.

    Slots are counted from stamp 0, so a 30 fps camera limited to 10 Hz logs exactly every
    third frame whatever its jitter, live and offline alike. ``hz`` 0 lets every frame
    through. Either way a frame whose stamp equals the last one let through on its entity is
    a repeat (an ``echo`` relay of the same frame) and is held back. A stamp that goes back
    in time (a replay starting over) lands in another slot and passes.
    """

    def __init__(self, hz: float):
        self.period_ns = round(1e9 / hz) if hz > 0 else 0
        self._last: dict[str, int] = {}

    def admit(self, entity: str, stamp_ns: int) -> bool:
        last = self._last.get(entity)
        if last is not None and (stamp_ns == last or
                                 (self.period_ns and stamp_ns // self.period_ns == last // self.period_ns)):
            return False
        self._last[entity] = stamp_ns
        return True
