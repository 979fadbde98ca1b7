"""Procedural, feature-rich grey textures: blobs, boxes, lines and text at many scales.

Good for keypoint detectors and SLAM: corners and blobs everywhere, no repeating period.
"""

from __future__ import annotations

import cv2
import numpy as np

TEXEL_AREA_PER_SHAPE = 900
WORDS = ("artrack", "ZENOH", "pose", "SLAM", "42", "marker", "IR", "ORB", "sift", "map", "K=3x3", "T_a_b")


def procedural_texture(rng: np.random.Generator, width: int, height: int) -> np.ndarray:
    """A (height, width) uint8 texture drawn from ``rng``: a smooth background and random shapes.

    Shapes span 3 px to a quarter of the shorter side (log-uniform), so it has detail at every
    pyramid level; anti-aliased and lightly blurred so it warps without aliasing.
    """
    coarse = rng.uniform(60, 190, (4, 4)).astype(np.float32)
    image = cv2.resize(coarse, (width, height), interpolation=cv2.INTER_CUBIC).clip(0, 255).astype(np.uint8)
    largest = max(min(width, height) / 4, 4.0)
    for _ in range(width * height // TEXEL_AREA_PER_SHAPE):
        size = float(np.exp(rng.uniform(np.log(3.0), np.log(largest))))
        draw_shape(image, rng, rng.uniform((0, 0), (width, height)), size)
    return cv2.GaussianBlur(image, (0, 0), 0.6)


def draw_shape(image: np.ndarray, rng: np.random.Generator, centre: np.ndarray, size: float) -> None:
    """Draw one random shape (disc, ellipse, box, line or word) of about ``size`` px at ``centre``, in place."""
    colour = int(rng.integers(0, 256))
    x, y = (int(c) for c in centre)
    half = max(int(size / 2), 1)
    kind = int(rng.integers(5))
    if kind == 0:
        cv2.circle(image, (x, y), half, colour, -1, cv2.LINE_AA)
    elif kind == 1:
        axes = (half, max(int(half * rng.uniform(0.2, 1.0)), 1))
        cv2.ellipse(image, (x, y), axes, float(rng.uniform(0, 180)), 0, 360, colour, -1, cv2.LINE_AA)
    elif kind == 2:
        corners = cv2.boxPoints(((x, y), (size, size * rng.uniform(0.2, 1.0)), float(rng.uniform(0, 90))))
        cv2.fillConvexPoly(image, np.round(corners).astype(np.int32), colour, cv2.LINE_AA)
    elif kind == 3:
        angle = rng.uniform(0, np.pi)
        dx, dy = int(half * np.cos(angle)), int(half * np.sin(angle))
        thickness = max(1, int(size / 12))
        cv2.line(image, (x - dx, y - dy), (x + dx, y + dy), colour, thickness, cv2.LINE_AA)
    else:
        word = WORDS[int(rng.integers(len(WORDS)))]
        scale = size / 30.0
        cv2.putText(image, word, (x, y), cv2.FONT_HERSHEY_SIMPLEX, scale, colour, max(1, int(scale * 2)), cv2.LINE_AA)
