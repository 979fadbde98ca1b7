"""The tuning numbers of the SLAM system: one set for every camera and sequence."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field

__all__ = ["SlamSettings"]


class SlamSettings(BaseModel):
    """Features: ``max_keypoints`` ORB keypoints spread over a grid, a pyramid of ``levels`` levels
    each ``scale_factor`` smaller, FAST threshold ``fast_threshold`` (grey levels).

    Initialisation: a reference frame is matched with each new frame (keypoints within
    ``init_window_px``, descriptor distance at most ``match_max_distance``, ratio ``init_ratio``)
    until ``services.slam.initialisation.initialise`` accepts the pair; the reference is replaced
    after ``reference_max_age`` frames, or at once when it has too few matches. A map starts only
    with ``init_min_points`` points. A pair needs the median parallax of ``InitialisationSettings``
    (1 deg) until the new frame is ``init_late_frames`` frames after the reference, then only
    ``init_late_parallax_deg``. A map started under the full bound is young: until it has
    ``young_map_keyframes`` keyframes, a tracked frame as far from the last keyframe as the first two
    keyframes are apart becomes one (with the mapper idle). A map lost with at most ``restart_keyframes``
    keyframes is given up for a new one (``services.slam.system``).

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

    Loop closing (``loop.closing``, with ``loop_closing``): a place candidate found for
    ``loop_consistency`` keyframes in a row before the current one is verified by a Sim(3) and accepted
    with ``loop_min_inliers`` matches; the loop is then corrected, fused, the pose graph optimised and
    the whole map bundle adjusted.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    max_keypoints: int = Field(default=1500, ge=1, description="ORB keypoints per frame, spread over a grid")
    levels: int = Field(default=8, ge=1, le=32, description="levels of the ORB pyramid")
    scale_factor: float = Field(default=1.2, gt=1, le=4, description="scale between pyramid levels")
    fast_threshold: int = Field(default=20, ge=1, le=255, description="ORB's FAST threshold, grey levels")
    match_max_distance: int = Field(default=64, ge=0, le=256, description="largest descriptor distance of an "
                                                                           "initialisation or relocalisation match, "
                                                                           "bits")
    match_ratio: float = Field(default=0.8, gt=0, le=1, description="ratio test of matches with the local map and "
                                                                    "of relocalisation")
    init_window_px: float = Field(default=100.0, gt=0, description="initialisation: search window around a "
                                                                   "reference keypoint, px")
    init_ratio: float = Field(default=0.9, gt=0, le=1, description="initialisation: ratio test")
    reference_max_age: int = Field(default=30, ge=1, description="initialisation: frames before the reference "
                                                                 "frame is replaced")
    init_min_points: int = Field(default=80, ge=1, description="initialisation: points a first map needs")
    init_late_frames: int = Field(default=4, ge=1, description="initialisation: frames after the reference from "
                                                               "which a pair needs only init_late_parallax_deg")
    init_late_parallax_deg: float = Field(default=0.4, ge=0, description="initialisation: least median parallax "
                                                                          "of a pair init_late_frames or more "
                                                                          "frames apart, deg")
    young_map_keyframes: int = Field(default=6, ge=2, description="keyframes a map started under the full "
                                                                  "parallax bound makes one initial baseline "
                                                                  "apart")
    restart_keyframes: int = Field(default=5, ge=0, description="a map of its own lost with at most this many "
                                   "keyframes is given up for a new one, placed where the camera's motion carries "
                                   "it (0: never)")
    projection_max_distance: int = Field(default=100, ge=0, le=256, description="largest descriptor distance of a "
                                                                                "match found by projection, bits")
    motion_window_px: float = Field(default=15.0, gt=0, description="tracking: search window around the "
                                                                    "constant-velocity prediction, px per level "
                                                                    "scale")
    motion_ratio: float = Field(default=0.9, gt=0, le=1, description="tracking: ratio test of the search by "
                                                                     "projection")
    min_motion_matches: int = Field(default=20, ge=1, description="tracking: inliers that keep the motion's "
                                                                  "refined pose (fewer: the window is doubled)")
    min_motion_inliers: int = Field(default=10, ge=1, description="tracking: inliers the motion's pose needs "
                                                                  "when PnP fails")
    pnp_threshold_px: float = Field(default=4.0, gt=0, description="tracking: PnP RANSAC's inlier threshold, px")
    pnp_min_inliers: int = Field(default=20, ge=1, description="tracking: inliers a PnP pose needs")
    local_keyframes: int = Field(default=20, ge=1, description="keyframes of the local map searched")
    local_window_px: float = Field(default=4.0, gt=0, description="search window of the local map around the "
                                                                  "pose, px per level scale")
    local_ratio: float = Field(default=0.8, gt=0, le=1, description="ratio test of the local map's search")
    min_tracked: int = Field(default=30, ge=1, description="inliers under which a frame is lost")
    keyframe_ratio: float = Field(default=0.9, gt=0, le=1, description="a frame tracking under this share of its "
                                                                       "reference keyframe's well-seen points may "
                                                                       "become a keyframe")
    min_keyframe_gap_s: float = Field(default=0.5, ge=0, description="least time between keyframes with the "
                                                                     "mapper idle, s")
    max_keyframe_gap_s: float = Field(default=1.0, ge=0, description="time after which a frame becomes a "
                                                                     "keyframe anyway, s")
    triangulation_neighbours: int = Field(default=10, ge=1, description="best covisible keyframes new points are "
                                                                        "triangulated with")
    triangulation_max_distance: int = Field(default=50, ge=0, le=256, description="largest descriptor distance of "
                                                                                  "a triangulated match, bits")
    triangulation_ratio: float = Field(default=0.8, gt=0, le=1, description="ratio test of triangulated matches")
    min_parallax_deg: float = Field(default=1.0, ge=0, description="least angle between the rays of a new "
                                                                   "point, deg")
    cull_found_ratio: float = Field(default=0.25, ge=0, le=1, description="a new point found in under this share "
                                                                          "of the frames it was visible in is "
                                                                          "culled")
    cull_min_observations: int = Field(default=3, ge=1, description="keyframes a new point must be observed by")
    ba_window: int = Field(default=10, ge=2, description="keyframes of a local bundle adjustment")
    ba_iterations: int = Field(default=10, ge=1, description="iterations of a local bundle adjustment")
    reloc_candidates: int = Field(default=5, ge=1, description="relocalisation: keyframes tried, ranked by votes")
    reloc_min_inliers: int = Field(default=50, ge=1, description="relocalisation: inliers a pose needs")
    reloc_window_px: float = Field(default=10.0, gt=0, description="relocalisation: search window, px per level "
                                                                   "scale")
    loop_closing: bool = Field(default=True, description="look for loops and close them (after local mapping)")
    loop_consistency: int = Field(default=2, ge=0, description="loop closing: keyframes in a row before the "
                                                               "current one that must find a candidate's place")
    loop_min_inliers: int = Field(default=40, ge=3, description="loop closing: matches that accept a loop's Sim(3)")
