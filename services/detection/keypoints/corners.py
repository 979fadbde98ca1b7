"""Harris and Shi-Tomasi corners over a scale pyramid, with ORB's sizes and orientations.

Pixels are those of the input image: x right, y down, the centre of the top-left pixel at (0, 0).

The pyramid is ORB's: level ``l`` is ``round(W / s^l)`` by ``round(H / s^l)`` for a scale factor
``s``, here resized from the full image with pixel-area averaging, down to levels of
``PATCH_PX`` px. On each level the response map of ``services.detection.keypoints.harris`` (Harris's
``det - k trace^2`` or the smaller eigenvalue) is searched for corners: pixels whose response is
the largest of their 3x3 neighbours, positive, and more than ``quality`` times the level's
largest; their response is taken as that fraction. As ORB does, a level keeps at most its
share of the corners asked for, the shares falling by ``1 / s`` a level (gradients grow as a
blurred image shrinks, so by their raw responses the coarse levels would take most places). A
parabola through the neighbours' responses places each corner to a fraction of a pixel (along
x and y apart), and it maps back to the full image as ``(x_l + 0.5) W / W_l - 0.5`` (pixel
centres, so a corner keeps its place across levels).

A corner's keypoint takes ORB's conventions so ORB's extractor describes it as it would its own
keypoints: size ``PATCH_PX * s^l`` (the patch ORB describes at that level), octave ``l``, and
angle the direction of the intensity centroid of the disc of radius ``PATCH_PX // 2`` around
it on its level (Rosin's orientation, ORB's).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np

from services.detection.keypoints.harris import harris_response, min_eigenvalue

__all__ = ["PATCH_PX", "Corners", "corner_keypoints", "find_corners", "intensity_centroid_angles", "level_corners",
           "level_shares", "pyramid"]

PATCH_PX = 31
"""ORB's patch side: the size of a keypoint found on pyramid level 0."""

CornerMeasure = Literal["harris", "shi_tomasi"]


@dataclass(frozen=True)
class Corners:
    """Corner candidates of one image, strongest first.

    ``points``: (N, 2) float32 px of the full image; ``level_points``: (N, 2) float32 px of
    their pyramid level; ``responses``: (N,) float32; ``levels``: (N,) int32.
    """

    points: np.ndarray
    level_points: np.ndarray
    responses: np.ndarray
    levels: np.ndarray

    def __len__(self) -> int:
        return len(self.points)

    def select(self, keep: np.ndarray) -> Corners:
        """The candidates ``keep`` picks: an (N,) bool mask or an index array."""
        return Corners(self.points[keep], self.level_points[keep], self.responses[keep], self.levels[keep])


def pyramid(grey: np.ndarray, levels: int, scale_factor: float) -> list[np.ndarray]:
    """Up to ``levels`` images: the (H, W) ``grey``, then its reductions by ``scale_factor^l`` while both sides
    keep at least ``PATCH_PX`` px."""
    height, width = grey.shape
    images = [grey]
    for level in range(1, levels):
        size = (round(width / scale_factor ** level), round(height / scale_factor ** level))
        if min(size) < PATCH_PX:
            break
        images.append(cv2.resize(grey, size, interpolation=cv2.INTER_AREA))
    return images


def level_shares(count: int, levels: int, scale_factor: float) -> np.ndarray:
    """(levels,) int64 summing to ``count``: ORB's shares, proportional to ``scale_factor^-l``."""
    weights = scale_factor ** -np.arange(levels, dtype=np.float64)
    shares = np.floor(count * weights / weights.sum()).astype(np.int64)
    shares[0] += count - shares.sum()
    return shares


def find_corners(images: list[np.ndarray], measure: CornerMeasure, count: int, scale_factor: float,
                 quality: float = 0.01, block_size: int = 3, k: float = 0.04, margin: float = 0.0) -> Corners:
    """At most ``count`` corners of ``images`` (a ``pyramid`` of ``scale_factor``), each level's strongest up to
    its ``level_shares``, at least ``margin`` px inside the full image."""
    height, width = images[0].shape
    parts = []
    for level, (image, share) in enumerate(zip(images, level_shares(count, len(images), scale_factor), strict=True)):
        xy, response = level_corners(image, measure, quality, block_size, k)
        full = (xy + 0.5) * np.array([width / image.shape[1], height / image.shape[0]], np.float32) - 0.5
        inside = np.flatnonzero(np.all((full >= margin) & (full <= np.array([width, height]) - 1 - margin), axis=1))
        kept = inside[np.argsort(-response[inside], kind="stable")[:share]]
        parts.append((full[kept], xy[kept], response[kept], np.full(len(kept), level, np.int32)))
    points, level_points, responses, levels = (np.concatenate(part) for part in zip(*parts, strict=True))
    return Corners(points, level_points, responses, levels).select(np.argsort(-responses, kind="stable"))


def level_corners(image: np.ndarray, measure: CornerMeasure, quality: float = 0.01, block_size: int = 3,
                  k: float = 0.04) -> tuple[np.ndarray, np.ndarray]:
    """(M, 2) float32 sub-pixel corners of one (H, W) uint8 image, in its px, and their (M,) float32 responses
    as fractions of the image's largest response, in (quality, 1]."""
    response = harris_response(image, block_size, 3, k) if measure == "harris" else min_eigenvalue(image, block_size, 3)
    peak = float(response.max())
    is_peak = (response == cv2.dilate(response, np.ones((3, 3), np.uint8))) & (response > max(quality * peak, 0.0))
    rows, columns = np.nonzero(is_peak[1:-1, 1:-1])
    rows += 1
    columns += 1
    centre = response[rows, columns]
    dx = _parabola_vertex(response[rows, columns - 1], centre, response[rows, columns + 1])
    dy = _parabola_vertex(response[rows - 1, columns], centre, response[rows + 1, columns])
    return np.column_stack([columns + dx, rows + dy]).astype(np.float32), (centre / np.float32(peak)).astype(np.float32)


def _parabola_vertex(before: np.ndarray, centre: np.ndarray, after: np.ndarray) -> np.ndarray:
    """(M,) float32 offsets in [-0.5, 0.5] of the vertex of the parabola through three samples 1 px apart."""
    curvature = before - 2 * centre + after
    safe = np.where(curvature < 0, curvature, -1.0)
    return np.where(curvature < 0, np.clip(0.5 * (before - after) / safe, -0.5, 0.5), 0.0).astype(np.float32)


def _disc(radius: int) -> tuple[np.ndarray, np.ndarray]:
    dy, dx = np.mgrid[-radius:radius + 1, -radius:radius + 1]
    inside = dx * dx + dy * dy <= radius * radius
    return dx[inside].astype(np.float32), dy[inside].astype(np.float32)


_DISC = _disc(PATCH_PX // 2)


def intensity_centroid_angles(image: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(M,) float32 degrees in [0, 360): from each of the (M, 2) ``points`` (px of the (H, W) ``image``,
    taken at the nearest pixel) towards the intensity centroid of the disc of radius ``PATCH_PX // 2``
    around it, ``atan2(m01, m10)`` (clockwise in the image, OpenCV's keypoint angle). The image is
    mirrored beyond its border."""
    radius = PATCH_PX // 2
    padded = cv2.copyMakeBorder(image, radius, radius, radius, radius, cv2.BORDER_REFLECT_101)
    centres = np.rint(points).astype(np.int64) + radius
    dx, dy = _DISC
    values = padded[centres[:, 1:2] + dy.astype(np.int64), centres[:, 0:1] + dx.astype(np.int64)].astype(np.float32)
    return np.mod(np.degrees(np.arctan2(values @ dy, values @ dx)), 360.0).astype(np.float32)


def corner_keypoints(images: list[np.ndarray], corners: Corners, scale_factor: float) -> list[cv2.KeyPoint]:
    """OpenCV keypoints of ``corners`` found on ``images`` (a ``pyramid`` of ``scale_factor``): size
    ``PATCH_PX * scale_factor^level``, octave the level, angle the intensity centroid's on the level."""
    angles = np.zeros(len(corners), np.float32)
    for level, image in enumerate(images):
        on_level = corners.levels == level
        if on_level.any():
            angles[on_level] = intensity_centroid_angles(image, corners.level_points[on_level])
    sizes = PATCH_PX * scale_factor ** corners.levels.astype(np.float64)
    return [cv2.KeyPoint(float(x), float(y), float(size), float(angle), float(response), int(level))
            for (x, y), size, angle, response, level
            in zip(corners.points, sizes, angles, corners.responses, corners.levels, strict=True)]
