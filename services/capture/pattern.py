"""A moving test pattern: the simplest synthetic source, deterministic per frame index.

A dim vertical gradient with a bright disc travelling along a Lissajous path and the
frame number printed in a corner. Pure numpy/OpenCV, no bus.
"""

from __future__ import annotations

import cv2
import numpy as np

DEFAULT_K = (600.0, 0.0, 319.5, 0.0, 600.0, 239.5, 0.0, 0.0, 1.0)


def disc_centre(index: int, width: int, height: int) -> tuple[float, float]:
    """Pixel centre ``(u, v)`` of the disc in frame ``index``."""
    t = index / 30.0
    return (width / 2 + 0.35 * width * np.sin(1.3 * t), height / 2 + 0.35 * height * np.sin(2.1 * t + 0.5))


def render_pattern(index: int, width: int = 640, height: int = 480) -> np.ndarray:
    """Frame ``index`` of the pattern: (height, width) uint8."""
    gradient = np.linspace(20, 90, height, dtype=np.float32)[:, None]
    image = np.broadcast_to(gradient, (height, width)).astype(np.uint8)
    u, v = disc_centre(index, width, height)
    shift = 4  # sub-pixel placement: coordinates in 1/16 px
    centre = (int(round(u * (1 << shift))), int(round(v * (1 << shift))))
    cv2.circle(image, centre, max(4, height // 24) << shift, 250, thickness=-1, lineType=cv2.LINE_AA, shift=shift)
    cv2.putText(image, f"{index:06d}", (8, height - 10), cv2.FONT_HERSHEY_SIMPLEX, 0.6, 200, 1, cv2.LINE_AA)
    return image
