"""Map points projected into a camera view, and matched there to its keypoints (ORB-SLAM's search by
projection).

A point is in the view when it is in front of the camera, projects inside the image, lies within
the distances its descriptor can be found at (``MapPoint.min_distance`` / ``max_distance``, with
20 % slack) and is seen within 60 deg of its mean viewing direction. Its pyramid level is
predicted from its distance: ``ceil(log(max_distance / distance) / log(scale_factor))``; the
search window grows with that level's scale.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.slam.features import FrameFeatures
from services.slam.map.map_point import PointArrays
from services.slam.matching import search_by_projection

__all__ = ["Projected", "project_points", "search_projected"]

MIN_VIEW_COS = 0.5
"""A point is searched for only when seen within 60 deg of its mean viewing direction."""
DISTANCE_SLACK = (0.8, 1.2)


@dataclass(frozen=True)
class Projected:
    """The V of P points that fall in a view: ``rows`` (V,) int64 into the points, ``pixels`` (V, 2) px,
    ``levels`` (V,) predicted pyramid levels, ``view_cos`` (V,) cosine of the angle between the
    viewing ray and the point's mean viewing direction."""

    rows: np.ndarray
    pixels: np.ndarray
    levels: np.ndarray
    view_cos: np.ndarray


def project_points(points: PointArrays, T_camera_world: np.ndarray, K: np.ndarray, size: tuple[int, int],
                   scale_factor: float, levels: int) -> Projected:
    """Which of ``points`` a camera at ``T_camera_world`` (4, 4) with intrinsics ``K`` (3, 3) and image
    ``size`` (width, height) px sees, where, and at which level."""
    camera = points.positions @ T_camera_world[:3, :3].T + T_camera_world[:3, 3]
    depth = camera[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        pixels = (camera[:, :2] / depth[:, None]) @ K[:2, :2].T + K[:2, 2]
    centre = -T_camera_world[:3, :3].T @ T_camera_world[:3, 3]
    rays = points.positions - centre
    distance = np.linalg.norm(rays, axis=1)
    view_cos = np.sum(rays * points.normals, axis=1) / np.maximum(distance, 1e-12)
    width, height = size
    inside = ((depth > 0) & (pixels[:, 0] >= 0) & (pixels[:, 0] <= width - 1) & (pixels[:, 1] >= 0)
              & (pixels[:, 1] <= height - 1) & (distance >= DISTANCE_SLACK[0] * points.min_distances)
              & (distance <= DISTANCE_SLACK[1] * points.max_distances) & (view_cos >= MIN_VIEW_COS))
    rows = np.flatnonzero(inside)
    with np.errstate(divide="ignore"):
        level = np.ceil(np.log(points.max_distances[rows] / distance[rows]) / np.log(scale_factor))
    return Projected(rows, pixels[rows], np.clip(level, 0, levels - 1).astype(np.int64), view_cos[rows])


def search_projected(points: PointArrays, projected: Projected, features: FrameFeatures, available: np.ndarray,
                     window_px: float, scale_factor: float, max_distance: int,
                     ratio: float) -> tuple[np.ndarray, np.ndarray]:
    """``(point rows, keypoint indices)`` (M,) int64: the projected points matched to free keypoints
    (``available`` (N,) bool) within ``window_px`` times their predicted level's scale
    (``matching.search_by_projection``)."""
    radii = window_px * np.power(scale_factor, projected.levels.astype(np.float64))
    rows, keypoints = search_by_projection(projected.pixels, radii, projected.levels,
                                           points.descriptors[projected.rows], features.pixels, features.levels,
                                           features.descriptors, available, max_distance, ratio)
    return projected.rows[rows], keypoints
