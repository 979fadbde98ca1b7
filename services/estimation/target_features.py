"""Keypoints and descriptors for image targets: a small OpenCV front end behind one interface.

An ``Extractor`` is any callable ``extract(grey) -> (points, descriptors)``: ``grey`` is an (H, W)
uint8 image; ``points`` (N, 2) float32 pixels (the centre of the top-left pixel at (0, 0));
``descriptors`` (N, D), uint8 for binary descriptors (compared by Hamming distance) or float32
(compared by L2 distance). Targets, the trackability check and recognition take any such callable,
so another detector plugs in without touching them; ``make_extractor`` builds the two kept here:
``orb`` (the default: fast, binary, 256 bits) and ``sift`` (slower, float, 128 dimensions).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Literal, get_args

import cv2
import numpy as np

__all__ = [
    "DEFAULT_FEATURE",
    "DEFAULT_MAX_FEATURES",
    "FEATURES",
    "Extractor",
    "Feature",
    "is_binary",
    "make_extractor",
    "to_grey",
]

Extractor = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]
Feature = Literal["orb", "sift"]
FEATURES: tuple[Feature, ...] = get_args(Feature)
DEFAULT_FEATURE: Feature = "orb"
DEFAULT_MAX_FEATURES = 2000
"""Keypoints per image (per pyramid level for a target): enough for a 640x480 frame to cover a target
seen small, few enough that brute-force matching stays a few milliseconds."""
ORB_FAST_THRESHOLD = 12
"""FAST threshold of ORB (OpenCV's default is 20): lower finds corners in soft, defocused views."""


def make_extractor(feature: str = DEFAULT_FEATURE, max_features: int = DEFAULT_MAX_FEATURES) -> Extractor:
    """The extractor named ``feature`` (one of ``FEATURES``) keeping at most ``max_features`` keypoints."""
    if feature not in FEATURES:
        raise ValueError(f"feature {feature!r}: must be one of {', '.join(FEATURES)}")
    if max_features < 1:
        raise ValueError(f"max_features must be >= 1, got {max_features}")
    detector = (cv2.ORB.create(nfeatures=max_features, fastThreshold=ORB_FAST_THRESHOLD) if feature == "orb"
                else cv2.SIFT.create(nfeatures=max_features))
    dimension = 32 if feature == "orb" else 128
    dtype = np.uint8 if feature == "orb" else np.float32

    def extract(grey: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        keypoints, descriptors = detector.detectAndCompute(grey, None)
        if descriptors is None or not keypoints:
            return np.zeros((0, 2), np.float32), np.zeros((0, dimension), dtype)
        return np.array([k.pt for k in keypoints], np.float32).reshape(-1, 2), descriptors.astype(dtype, copy=False)

    return extract


def is_binary(descriptors: np.ndarray) -> bool:
    """Whether (N, D) descriptors are binary (uint8, Hamming distance) rather than float (L2 distance)."""
    return bool(descriptors.dtype == np.uint8)


def to_grey(image: np.ndarray) -> np.ndarray:
    """(H, W) uint8 of an (H, W) or (H, W, 3) BGR image, uint8 or uint16 (16-bit scaled by 1/257).

    Raises ValueError for any other shape or dtype, or an empty image.
    """
    image = np.asarray(image)
    if image.size == 0 or not (image.ndim == 2 or (image.ndim == 3 and image.shape[2] in (1, 3))):
        raise ValueError(f"image must be (H, W) or (H, W, 3) and not empty, got shape {image.shape}")
    if image.dtype == np.uint16:
        image = (image.astype(np.float32) / 257.0 + 0.5).astype(np.uint8)
    elif image.dtype != np.uint8:
        raise ValueError(f"image must be uint8 or uint16, got {image.dtype}")
    if image.ndim == 3:
        image = image[..., 0] if image.shape[2] == 1 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    return np.ascontiguousarray(image)
