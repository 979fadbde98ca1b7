"""Keypoints and descriptors of one grey image, by one of five methods, spread over the image.

``detector`` holds the methods, ``corners`` and ``harris`` the corner detector written out, ``spread`` grid
bucketing and ANMS, and ``node`` is the keypoints node."""

from __future__ import annotations

from services.detection.keypoints.corners import Corners, find_corners
from services.detection.keypoints.detector import KeypointDetector, KeypointParams, Keypoints, detect_keypoints
from services.detection.keypoints.spread import spread_anms, spread_grid

__all__ = [
    "Corners",
    "KeypointDetector",
    "KeypointParams",
    "Keypoints",
    "detect_keypoints",
    "find_corners",
    "spread_anms",
    "spread_grid",
]
