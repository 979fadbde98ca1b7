"""Grey levels of a camera frame, as the detectors take them.

Frames arrive as mono8 ``(H, W)`` uint8, mono16 ``(H, W)`` uint16, or bgr8 / bgra8
``(H, W, 3|4)`` uint8 (OpenCV's channel order).
"""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["MONO16_SCALE", "as_grey", "as_grey8"]

MONO16_SCALE = 257.0
"""A mono16 grey level per mono8 grey level (65535 / 255)."""


def as_grey(data: np.ndarray) -> np.ndarray:
    """(H, W) grey levels of a mono (H, W) or BGR(A) (H, W, 3|4) frame, in the frame's dtype."""
    if data.ndim == 3:
        return cv2.cvtColor(data, cv2.COLOR_BGR2GRAY if data.shape[2] == 3 else cv2.COLOR_BGRA2GRAY)
    return data


def as_grey8(data: np.ndarray) -> np.ndarray:
    """(H, W) uint8 grey levels of any frame ``as_grey`` takes; mono16 is scaled by 1 / ``MONO16_SCALE``."""
    grey = as_grey(data)
    if grey.dtype == np.uint16:
        return cv2.convertScaleAbs(grey, alpha=1.0 / MONO16_SCALE)
    return grey
