"""Image targets as data: a printed image, its size in metres and its features on the target plane.

Target frame (the ArUco marker frame): origin at the image's centre, x right, y up, z out of the
image towards the viewer. Pixel centres are at integer coordinates, the top-left pixel's at
(0, 0), so a W x H image spans [-0.5, W - 0.5] x [-0.5, H - 0.5] pixels and its pixel (u, v) lies at

    x = (u - (W - 1) / 2) * s,   y = -(v - (H - 1) / 2) * s,   z = 0,   s = width_m / W  (metres per pixel)

and the image's outer edges at x = +-width_m / 2, y = +-height_m / 2 with ``height_m = H * s``.

Keypoints are found over a scale pyramid of the image (each level half the previous one's size, down
to ``MIN_LEVEL_SIDE`` pixels), so a frame that sees the target small still finds features of its
own scale; every keypoint is stored in level-0 pixels with the level it came from. A detector with a
scale space of its own (SIFT, AKAZE: ``target_features.has_scale_space``) already finds those features
in the full image, so its target is that image alone (``target_levels``): a pyramid over it would only
repeat its keypoints at every level, and the copies of one feature would make each other's matches
fail the ratio test.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from services.detection.keypoints.detector import KeypointParams
from services.estimation.targets.features import (
    DEFAULT_FEATURE,
    Extractor,
    feature_params,
    has_scale_space,
    make_extractor,
    to_grey,
)

__all__ = [
    "MAX_LEVELS",
    "MIN_LEVEL_SIDE",
    "MIN_TARGET_SIDE",
    "Target",
    "build_target",
    "check_width",
    "pyramid_features",
    "target_features",
    "target_levels",
    "target_points",
]

MIN_LEVEL_SIDE = 160
"""A pyramid level whose shorter side would fall below this many pixels is not made (too few features)."""
MAX_LEVELS = 4
"""Pyramid levels at most: level k is the image scaled by 2^-k (with ORB's own finer pyramid inside each);
one for a scale-space detector (``target_levels``)."""
MIN_TARGET_SIDE = 32
"""Images with a shorter side below this many pixels are refused as targets."""


@dataclass(frozen=True)
class Target:
    """One image target.

    ``name``; ``image``: (H, W) uint8 grey image; ``width_m``: the printed width, metres;
    ``detector``: the settings that found the keypoints (a frame's must be found alike; ``feature`` names
    its method);
    ``keypoints``: (N, 2) float32 level-0 image pixels; ``levels``: (N,) uint8 pyramid level of each;
    ``descriptors``: (N, D) uint8 (binary) or float32; ``points``: (N, 3) float64 target frame, metres.
    """

    name: str
    image: np.ndarray
    width_m: float
    detector: KeypointParams
    keypoints: np.ndarray
    levels: np.ndarray
    descriptors: np.ndarray
    points: np.ndarray

    @property
    def feature(self) -> str:
        """The detector's method (``orb``, ``sift``, ...)."""
        return self.detector.method

    @property
    def size_px(self) -> tuple[int, int]:
        """(width, height) of the image, pixels."""
        return self.image.shape[1], self.image.shape[0]

    @property
    def metres_per_pixel(self) -> float:
        return self.width_m / self.image.shape[1]

    @property
    def height_m(self) -> float:
        return self.image.shape[0] * self.metres_per_pixel

    def corners(self) -> np.ndarray:
        """(4, 3) the image's outer corners in the target frame, ArUco order TL, TR, BR, BL."""
        x, y = self.width_m / 2, self.height_m / 2
        return np.array([[-x, y, 0.0], [x, y, 0.0], [x, -y, 0.0], [-x, -y, 0.0]])

    def plane_from_pixel(self) -> np.ndarray:
        """(3, 3) image pixel (u, v, 1) -> target-plane (x, y, 1), metres (the module's mapping)."""
        s = self.metres_per_pixel
        w, h = self.size_px
        return np.array([[s, 0.0, -s * (w - 1) / 2], [0.0, -s, s * (h - 1) / 2], [0.0, 0.0, 1.0]])


def target_points(pixels: np.ndarray, size_px: tuple[int, int], width_m: float) -> np.ndarray:
    """(N, 3) float64 target-frame points (metres, z = 0) of (N, 2) image pixels of a ``size_px`` = (W, H)
    image printed ``width_m`` wide."""
    pixels = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    w, h = size_px
    s = width_m / w
    points = np.zeros((len(pixels), 3))
    points[:, 0] = (pixels[:, 0] - (w - 1) / 2) * s
    points[:, 1] = -(pixels[:, 1] - (h - 1) / 2) * s
    return points


def pyramid_features(grey: np.ndarray, extract: Extractor,
                     max_levels: int = MAX_LEVELS) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(keypoints, descriptors, levels)`` of an (H, W) uint8 image over its scale pyramid.

    Level k is the image resized by 2^-k (area averaging, sides rounded), made while its shorter side
    stays at or above ``MIN_LEVEL_SIDE`` (level 0 always). Keypoints: (N, 2) float32 level-0 pixels (a
    level pixel p maps to (p + 0.5) * (level-0 side / level side) - 0.5 per axis); descriptors: (N, D);
    levels: (N,) uint8.
    """
    points, descriptors, levels = [], [], []
    h, w = grey.shape
    for level in range(max_levels):
        size = (max(round(w / 2**level), 1), max(round(h / 2**level), 1))
        if level and min(size) < MIN_LEVEL_SIDE:
            break
        level_image = cv2.resize(grey, size, interpolation=cv2.INTER_AREA) if level else grey
        found, described = extract(level_image)
        scale = np.array([w / size[0], h / size[1]])
        points.append((np.asarray(found, np.float64).reshape(-1, 2) + 0.5) * scale - 0.5)
        descriptors.append(described)
        levels.append(np.full(len(found), level, np.uint8))
    return (np.concatenate(points).astype(np.float32), np.concatenate(descriptors),
            np.concatenate(levels))


def target_levels(detector: KeypointParams) -> int:
    """Pyramid levels at most of a target found by ``detector``: 1 (the image alone) for a detector with its
    own scale space, ``MAX_LEVELS`` for any other."""
    return 1 if has_scale_space(detector) else MAX_LEVELS


def target_features(grey: np.ndarray, detector: KeypointParams, extract: Extractor | None = None,
                    max_levels: int | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``pyramid_features`` of an (H, W) uint8 image as a target of ``detector`` gets them: found by ``extract``
    (default the detector's own) over at most ``max_levels`` levels (default ``target_levels(detector)``)."""
    return pyramid_features(grey, extract or make_extractor(detector),
                            target_levels(detector) if max_levels is None else max_levels)


def build_target(name: str, image: np.ndarray, width_m: float, feature: str | KeypointParams = DEFAULT_FEATURE,
                 extract: Extractor | None = None, max_levels: int | None = None) -> Target:
    """The target ``name`` of ``image`` ((H, W) or (H, W, 3) BGR, uint8 or uint16) printed ``width_m`` wide.

    ``feature``: a feature's name (``feature_params``) or detector settings, recorded in the target for
    frames to be described alike; ``extract``: the keypoint extractor (default: those settings');
    ``max_levels``: of its pyramid (default ``target_levels`` of the settings). Raises
    ValueError for a width that is not a positive finite number, an image smaller than ``MIN_TARGET_SIDE``
    or one without any keypoint.
    """
    width_m = check_width(width_m)
    grey = to_grey(image)
    if min(grey.shape) < MIN_TARGET_SIDE:
        raise ValueError(f"target image is {grey.shape[1]}x{grey.shape[0]} px; it needs at least "
                         f"{MIN_TARGET_SIDE} px on each side")
    detector = feature_params(feature) if isinstance(feature, str) else feature
    keypoints, descriptors, levels = target_features(grey, detector, extract, max_levels)
    if len(keypoints) == 0:
        raise ValueError("target image has no keypoints (no texture to recognise it by)")
    size_px = (grey.shape[1], grey.shape[0])
    return Target(name, grey, width_m, detector, keypoints, levels, descriptors,
                  target_points(keypoints, size_px, width_m))


def check_width(width_m: object) -> float:
    """``width_m`` as a float when it is a positive finite number of metres; ValueError otherwise."""
    if isinstance(width_m, bool) or not (isinstance(width_m, (int, float)) and math.isfinite(width_m)
                                         and width_m > 0):
        raise ValueError(f"target width {width_m!r}: must be a positive number of metres")
    return float(width_m)
