"""Bridging a gap: a frame the map no longer reaches, placed from the last tracked frame.

A camera moving forward leaves its map points behind within a few frames. After frames dropped (a busy
machine) or a stretch the map did not cover, the next frame may see too few of them to be tracked, and
relocalisation cannot help: the camera never saw that place. The frame is then paired with the last
tracked frame as a map's first two frames are (``initialisation.initialise``: the two-view model chosen,
its inliers triangulated, the parallax checked), and the pair is put in the map's frame and scale: the
last frame's pose places it, and its scale is

* the median ratio of the map's depth to the pair's over the matches whose keypoint in the last frame is
  a map point, when there are at least ``MIN_SCALE_POINTS`` of them (and no bridge when those ratios
  spread by more than ``MAX_SCALE_SPREAD`` between their quartiles);
* else the distance the constant-velocity model predicts for the time between the two frames.

Frames: ``T_last_world`` and the result's ``T_camera_world`` are (4, 4) camera-from-world, OpenCV camera
frames; pixels are undistorted, of the camera's ``K`` (3, 3).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.geometry.se3 import invert, make_transform, transform_points
from services.slam.initialisation import InitialisationSettings, initialise

__all__ = ["MAX_SCALE_SPREAD", "MIN_SCALE_POINTS", "Bridge", "bridge_pair"]

MIN_SCALE_POINTS = 8
"""Matches onto map points that set a bridge's scale; with fewer, the predicted distance does."""
MAX_SCALE_SPREAD = 1.2
"""The largest ratio of the upper to the lower quartile of those matches' depth ratios (map / pair): more,
and the pair's depths are too uncertain (too little parallax) to carry the map on."""


@dataclass(frozen=True)
class Bridge:
    """A bridged pair of N matches: ``T_camera_world`` (4, 4) the new frame's pose; ``inliers`` (N,) bool,
    the matches triangulated; ``points_world`` (N, 3) their points in the map's frame and scale (NaN
    elsewhere); ``scale`` map units per unit of the pair's baseline; ``from_map`` whether the map's depths
    set it (else the predicted distance)."""

    T_camera_world: np.ndarray
    inliers: np.ndarray
    points_world: np.ndarray
    scale: float
    from_map: bool


def bridge_pair(K: np.ndarray, T_last_world: np.ndarray, pixels_last: np.ndarray, pixels_new: np.ndarray,
                map_points_world: np.ndarray, predicted_distance: float,
                settings: InitialisationSettings) -> Bridge | None:
    """The new frame's pose and points from N matches ``pixels_last[i]`` <-> ``pixels_new[i]`` ((N, 2)
    each), or None when the pair does not initialise (too few matches, too little parallax, ...), has no
    scale, or its depths disagree with the map's (``MAX_SCALE_SPREAD``). ``map_points_world`` (N, 3): the
    map point of each match's keypoint in the last frame (NaN rows where it has none);
    ``predicted_distance``: how far the camera moved between the two frames by the motion model, map
    units."""
    found = initialise(pixels_last, pixels_new, K, np.zeros(5), settings)
    if not found.initialised or found.T_second_first is None:
        return None
    inliers = found.inliers
    scaled_by_map = inliers & np.all(np.isfinite(map_points_world), axis=1)
    from_map = int(scaled_by_map.sum()) >= MIN_SCALE_POINTS
    if from_map:
        map_depths = transform_points(T_last_world, map_points_world[scaled_by_map])[:, 2]
        ratios = map_depths / found.points[scaled_by_map, 2]
        low, scale, high = (float(q) for q in np.percentile(ratios, [25, 50, 75]))
        if not high <= MAX_SCALE_SPREAD * low:
            return None
    else:
        scale = float(predicted_distance)
    if not (np.isfinite(scale) and scale > 0):
        return None
    T_new_last = make_transform(found.T_second_first[:3, :3], found.T_second_first[:3, 3] * scale)
    points = np.full_like(found.points, np.nan)
    points[inliers] = transform_points(invert(T_last_world), found.points[inliers] * scale)
    return Bridge(T_new_last @ T_last_world, inliers, points, scale, from_map)
