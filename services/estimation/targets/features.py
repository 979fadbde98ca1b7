"""Keypoints and descriptors for image targets, found by the project's one detector
(``services.detection.keypoints.detector``).

An ``Extractor`` is any callable ``extract(grey) -> (points, descriptors)``: ``grey`` is an (H, W)
uint8 image; ``points`` (N, 2) float32 pixels (the centre of the top-left pixel at (0, 0));
``descriptors`` (N, D), uint8 for binary descriptors (compared by Hamming distance) or float32
(compared by L2 distance). Targets, the trackability check and recognition take any such callable;
``make_extractor`` builds one from a ``KeypointDetector``. A target records the detector settings
it was built with (``KeypointParams``), so frames are described the same way.

Features (``FEATURES``): ``orb`` (the default: fast, binary, 256 bits) and ``sift`` (slower, float,
128 dimensions), each at the settings of ``feature_params``: at most ``DEFAULT_MAX_FEATURES``
keypoints, the strongest kept without spreading (a target's texture decides where they fall), and
for ORB a FAST threshold of ``ORB_FAST_THRESHOLD``.

Detectors with a scale space of their own (``SCALE_SPACE_METHODS``: SIFT's octaves of blurred images,
AKAZE's nonlinear one) find a feature at every scale of one image, so their cap counts keypoints per
``CAP_FRAME_PX`` (640x480) pixels of the image (``keypoint_cap``) rather than per image: a large
photograph keeps the keypoint density of a 640x480 frame instead of its strongest
``DEFAULT_MAX_FEATURES`` alone. ORB's pyramid (8 levels, 1.2 apart) spans under two octaves, and the
corner detectors work on ORB's, so their cap stays per image (and a target of theirs gets a pyramid of
its own, ``targets``).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Literal, get_args

import numpy as np

from services.detection.grey import as_grey8
from services.detection.keypoints.detector import KeypointDetector, KeypointParams

__all__ = [
    "CAP_FRAME_PX",
    "DEFAULT_FEATURE",
    "DEFAULT_MAX_FEATURES",
    "FEATURES",
    "ORB_FAST_THRESHOLD",
    "SCALE_SPACE_METHODS",
    "Extractor",
    "Feature",
    "feature_params",
    "has_scale_space",
    "is_binary",
    "keypoint_cap",
    "make_extractor",
    "to_grey",
]

Extractor = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]
Feature = Literal["orb", "sift"]
FEATURES: tuple[Feature, ...] = get_args(Feature)
DEFAULT_FEATURE: Feature = "orb"
DEFAULT_MAX_FEATURES = 2000
"""Keypoints per image (per pyramid level for an ORB target; per 640x480 pixels for a scale-space detector,
``keypoint_cap``): enough for a 640x480 frame to cover a target seen small, few enough that brute-force
matching stays a few milliseconds."""
ORB_FAST_THRESHOLD = 12
"""FAST threshold of ORB (OpenCV's default is 20): lower finds corners in soft, defocused views."""
SCALE_SPACE_METHODS = ("sift", "akaze")
"""Detector methods (``KeypointParams.method``) that build a scale space of their own from one image."""
CAP_FRAME_PX = (640, 480)
"""(width, height) of the image a scale-space detector's ``max_count`` is meant for (``keypoint_cap``)."""


def feature_params(feature: str = DEFAULT_FEATURE) -> KeypointParams:
    """The detector settings of the feature named ``feature`` (one of ``FEATURES``); ValueError otherwise."""
    if feature not in FEATURES:
        raise ValueError(f"feature {feature!r}: must be one of {', '.join(FEATURES)}")
    return KeypointParams(method=feature, max_count=DEFAULT_MAX_FEATURES, spread="none",
                          fast_threshold=ORB_FAST_THRESHOLD)


def has_scale_space(detector: KeypointParams) -> bool:
    """Whether ``detector``'s method finds keypoints over a scale space of its own (``SCALE_SPACE_METHODS``)."""
    return detector.method in SCALE_SPACE_METHODS


def keypoint_cap(detector: KeypointParams, shape: tuple[int, ...]) -> int:
    """Keypoints kept at most in an image of ``shape`` (H, W, ...): for a scale-space detector ``max_count``
    per area of ``CAP_FRAME_PX`` and never fewer than ``max_count``; ``max_count`` for any other."""
    if not has_scale_space(detector):
        return detector.max_count
    frame_area = CAP_FRAME_PX[0] * CAP_FRAME_PX[1]
    return max(detector.max_count, math.ceil(detector.max_count * shape[0] * shape[1] / frame_area))


def make_extractor(feature: str | KeypointParams = DEFAULT_FEATURE) -> Extractor:
    """The extractor of ``feature``: a name (``feature_params``) or a target's own detector settings, keeping
    at most ``keypoint_cap`` keypoints of each image."""
    params = feature_params(feature) if isinstance(feature, str) else feature
    detectors = {params.max_count: KeypointDetector(params)}

    def extract(grey: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        cap = keypoint_cap(params, grey.shape)
        if cap not in detectors:
            detectors[cap] = KeypointDetector(params.model_copy(update={"max_count": cap}))
        found = detectors[cap].detect(grey)
        return found.points, found.descriptors

    return extract


def is_binary(descriptors: np.ndarray) -> bool:
    """Whether (N, D) descriptors are binary (uint8, Hamming distance) rather than float (L2 distance)."""
    return bool(descriptors.dtype == np.uint8)


def to_grey(image: np.ndarray) -> np.ndarray:
    """(H, W) uint8 of an (H, W) or (H, W, 3) BGR image, uint8 or uint16 (``services.detection.grey.as_grey8``).

    Raises ValueError for any other shape or dtype, or an empty image.
    """
    image = np.asarray(image)
    if image.size == 0 or not (image.ndim == 2 or (image.ndim == 3 and image.shape[2] in (1, 3))):
        raise ValueError(f"image must be (H, W) or (H, W, 3) and not empty, got shape {image.shape}")
    if image.dtype not in (np.uint8, np.uint16):
        raise ValueError(f"image must be uint8 or uint16, got {image.dtype}")
    return np.ascontiguousarray(as_grey8(image[..., 0] if image.ndim == 3 and image.shape[2] == 1 else image))
