"""The tuning numbers of the SLAM system: one set for every camera and sequence."""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["SlamSettings"]


@dataclass(frozen=True)
class SlamSettings:
    """Features: ``max_keypoints`` ORB keypoints spread over a grid, a pyramid of ``levels`` levels
    each ``scale_factor`` smaller, FAST threshold ``fast_threshold`` (grey levels).

    Initialisation: a reference frame is matched with each new frame (keypoints within
    ``init_window_px``, descriptor distance at most ``match_max_distance``, ratio ``init_ratio``)
    until ``services.slam.initialisation.initialise`` accepts the pair; the reference is replaced
    after ``reference_max_age`` frames, or at once when it has too few matches. A map starts only
    with ``init_min_points`` points.

    Tracking: search by projection of the last frame's points around the constant-velocity
    prediction within ``motion_window_px`` (per level scale; doubled when under ``min_motion_matches``
    are found), descriptor distance at most ``projection_max_distance`` and ratio
    ``motion_ratio``, the pose refined on them kept with ``min_motion_matches`` inliers; else PnP
    (``cv2.solvePnPRansac``, SQPNP, ``pnp_threshold_px``) on descriptor matches with the local map,
    kept with at least ``pnp_min_inliers`` inliers; else the motion's pose with ``min_motion_inliers``
    inliers. Then the local map (``local_keyframes`` keyframes) is searched within ``local_window_px``
    (ratio ``local_ratio``) around the pose. A frame with fewer than ``min_tracked`` inliers is lost.

    Keyframes: a frame becomes one when it tracks under ``keyframe_ratio`` of the points its
    reference keyframe tracks well (seen by three keyframes or more) and at least
    ``min_keyframe_gap_s`` seconds passed since the last keyframe with the mapper idle, or
    ``max_keyframe_gap_s`` passed; or when it is about to be lost (under ``2 * min_tracked``).

    Mapping: new points from the unmatched keypoints of a keyframe and its ``triangulation_neighbours``
    best covisible keyframes (descriptor distance at most ``triangulation_max_distance``, ratio
    ``triangulation_ratio``, epipolar and reprojection chi-square bounds, rays at least
    ``min_parallax_deg`` apart); points made within three keyframes are culled when found in under
    ``cull_found_ratio`` of the frames they were visible in or observed by fewer than
    ``cull_min_observations`` keyframes. Local bundle adjustment over the keyframe and its
    ``ba_window - 1`` best covisible keyframes, ``ba_iterations`` iterations.

    Relocalisation (``relocalisation``): up to ``reloc_candidates`` keyframes ranked by descriptor
    votes; a pose is accepted with ``reloc_min_inliers`` inliers after a projection search within
    ``reloc_window_px`` (per level scale).
    """

    max_keypoints: int = 1500
    levels: int = 8
    scale_factor: float = 1.2
    fast_threshold: int = 20
    match_max_distance: int = 64
    match_ratio: float = 0.8
    init_window_px: float = 100.0
    init_ratio: float = 0.9
    reference_max_age: int = 30
    init_min_points: int = 80
    projection_max_distance: int = 100
    motion_window_px: float = 15.0
    motion_ratio: float = 0.9
    min_motion_matches: int = 20
    min_motion_inliers: int = 10
    pnp_threshold_px: float = 4.0
    pnp_min_inliers: int = 20
    local_keyframes: int = 20
    local_window_px: float = 4.0
    local_ratio: float = 0.8
    min_tracked: int = 30
    keyframe_ratio: float = 0.9
    min_keyframe_gap_s: float = 0.5
    max_keyframe_gap_s: float = 1.0
    triangulation_neighbours: int = 10
    triangulation_max_distance: int = 50
    triangulation_ratio: float = 0.8
    min_parallax_deg: float = 1.0
    cull_found_ratio: float = 0.25
    cull_min_observations: int = 3
    ba_window: int = 10
    ba_iterations: int = 10
    reloc_candidates: int = 5
    reloc_min_inliers: int = 50
    reloc_window_px: float = 10.0
