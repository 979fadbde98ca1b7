"""Relocalisation: the pose of a frame against the whole map when tracking is lost (or has not begun,
on a map loaded from a file).

1. **Candidate keyframes.** Each of the frame's ORB descriptors looks up its two nearest map
   points (their representative descriptors) in an LSH index (``cv2.FlannBasedMatcher``,
   ``LSH_INDEX``), kept under the distance bound and the ratio test; each point so matched votes
   for every keyframe observing it. The keyframes with the most votes (at least
   ``pnp_min_inliers``, at most ``reloc_candidates``) are the candidates. Against exhaustive
   matching (``matching.match_descriptors``, every keypoint against every point; figures in
   docs/slam.md) the LSH index is cheap to build (it is rebuilt whenever the map changed; never in
   localisation-only mode, where copying a large map's points would cost more), quicker to query,
   and finds nearly all of the exhaustive matches; votes only rank keyframes, so the approximate
   neighbour is enough, and its cost grows far slower than the exhaustive match's with the map's
   size. A bag of binary words (ORB-SLAM's
   DBoW2) needs a vocabulary trained offline; maps of a few thousand points do without.
2. **Pose.** For each candidate in turn, the frame is matched again with the points the candidate
   observes only (few distractors, so more matches pass the ratio test), and the matches whose
   keypoint orientation turned unlike most others between the candidate and the frame are dropped
   (``matching.rotation_consistent``): a frame of another place keeps too few for PnP and costs
   no RANSAC. PnP with RANSAC (``cv2.solvePnPRansac``, SQPNP) on those matches, then a robust
   pose-only refinement (``optimisation.refine_pose``) on the RANSAC inliers (``solve_pnp``).
3. **Confirmation.** The refined pose projects the points of the candidate's local map (it and its
   ``COVISIBLE_OF_CANDIDATE`` best covisible keyframes) into the frame; they are searched for
   around their projections (``projection.search_projected``, a window of ``reloc_window_px``) and
   the pose refined on every match. The candidate is accepted with at least
   ``reloc_min_inliers`` inliers; otherwise the next candidate is tried.

Reasons while it fails: ``no_candidates`` (no keyframe shares enough descriptors with the frame),
``too_few_matches`` (no candidate gave a PnP pose), ``not_confirmed`` (poses found, none confirmed).
Frames: ``T_camera_world`` (4, 4) maps the map's world into the camera (OpenCV camera frames).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np

from services.slam.features import FrameFeatures
from services.slam.map.covisibility import CovisibilityGraph
from services.slam.map.database import MapDatabase
from services.slam.map.map_point import PointArrays
from services.slam.matching import match_descriptors, rotation_consistent
from services.slam.optimisation import PoseRefinement, refine_pose
from services.slam.projection import Projected, project_points, search_projected
from services.slam.settings import SlamSettings
from services.slam.timing import stage_timer

__all__ = ["Relocalisation", "Relocaliser", "solve_pnp"]

logger = logging.getLogger(__name__)

FlannParams = dict[str, bool | int | float | str]
LSH_INDEX: FlannParams = {"algorithm": 6, "table_number": 6, "key_size": 12, "multi_probe_level": 1}
"""FLANN's LSH (algorithm 6): 6 hash tables of 12-bit keys, probing neighbouring buckets one bit away."""
LSH_SEARCH: FlannParams = {"checks": 50}
COVISIBLE_OF_CANDIDATE = 10
"""A candidate's local map: the candidate and this many of its best covisible keyframes."""
PNP_ITERATIONS, PNP_CONFIDENCE = 300, 0.999


@dataclass(frozen=True)
class Relocalisation:
    """``T_camera_world`` (4, 4) or None; ``point_ids`` (N,) int64, the map point each keypoint matched
    (-1 for none); ``reason`` ("" when found, else ``no_candidates``, ``too_few_matches``,
    ``not_confirmed``); ``candidates`` keyframe ids tried, best first; ``keyframe_id`` the accepted
    one; ``inliers`` matches kept after confirmation (0 when not found)."""

    T_camera_world: np.ndarray | None
    point_ids: np.ndarray
    reason: str
    candidates: tuple[int, ...]
    keyframe_id: int | None = None
    inliers: int = 0


def solve_pnp(K: np.ndarray, settings: SlamSettings, positions: np.ndarray, features: FrameFeatures,
              keypoints: np.ndarray) -> tuple[PoseRefinement, np.ndarray] | None:
    """A camera pose from M matches of (M, 3) world ``positions`` with the frame's keypoints
    ``keypoints`` (M,): PnP RANSAC (SQPNP, ``pnp_threshold_px``) then ``refine_pose`` on its inliers.
    Returns the refinement and the (R,) indices into the M matches it was run on (its ``inliers`` (R,)
    bool refer to those), or None under ``pnp_min_inliers`` inliers at either step, or when OpenCV refuses
    the points (SQPNP asserts on a sample whose points nearly coincide)."""
    s = settings
    if len(keypoints) < s.pnp_min_inliers:
        return None
    try:
        ok, rvec, tvec, inliers = cv2.solvePnPRansac(positions, features.pixels[keypoints], K, None,
                                                     reprojectionError=s.pnp_threshold_px,
                                                     iterationsCount=PNP_ITERATIONS, confidence=PNP_CONFIDENCE,
                                                     flags=cv2.SOLVEPNP_SQPNP)
    except cv2.error as error:
        logger.debug("PnP on %d matches failed: %s", len(keypoints), str(error).strip().splitlines()[-1])
        return None
    if not ok or inliers is None or len(inliers) < s.pnp_min_inliers:
        return None
    used = inliers.ravel()
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = cv2.Rodrigues(rvec)[0], tvec.ravel()
    refined = refine_pose(K, T, positions[used], features.pixels[keypoints[used]],
                          features.sigmas[keypoints[used]])
    if np.count_nonzero(refined.inliers) < s.pnp_min_inliers:
        return None
    return refined, used


class Relocaliser:
    """Finds a lost frame's pose in ``slam_map`` for a camera of intrinsics ``K`` (3, 3) (undistorted
    pixels) and image ``size`` (width, height) px."""

    def __init__(self, slam_map: MapDatabase, K: np.ndarray, size: tuple[int, int], settings: SlamSettings):
        self.map = slam_map
        self.covisibility = CovisibilityGraph(slam_map)
        self.K = np.asarray(K, np.float64)
        self.size = size
        self.settings = settings
        self._index: tuple[int, np.ndarray, cv2.FlannBasedMatcher] | None = None

    def _point_index(self) -> tuple[np.ndarray, cv2.FlannBasedMatcher] | None:
        """(P,) ids of the map's points and an LSH index of their descriptors (row i is point ``ids[i]``),
        made again when the map's revision changed; None with fewer than two points."""
        with self.map.lock:
            revision = self.map.revision
            if self._index is None or self._index[0] != revision:
                points = self.map.arrays(np.array(sorted(self.map.points), np.int64))
                if len(points) < 2:
                    return None
                matcher = cv2.FlannBasedMatcher(LSH_INDEX, LSH_SEARCH)
                matcher.add([points.descriptors])
                matcher.train()
                self._index = (revision, points.ids, matcher)
            return self._index[1], self._index[2]

    def candidates(self, features: FrameFeatures) -> list[int]:
        """Keyframe ids ranked by the votes of the map points the frame's descriptors match, best
        first; only those with at least ``pnp_min_inliers`` votes, at most ``reloc_candidates``."""
        s = self.settings
        index = self._point_index()
        if index is None or len(features) == 0:
            return []
        ids, matcher = index
        pairs = matcher.knnMatch(features.descriptors, k=2)
        matched = {best.trainIdx for best, second in (m for m in pairs if len(m) == 2)
                   if best.distance <= s.match_max_distance and best.distance < s.match_ratio * second.distance}
        votes = self.covisibility.observers(ids[sorted(matched)])
        return [k for k, n in votes.most_common(s.reloc_candidates) if n >= s.pnp_min_inliers]

    def relocalise(self, features: FrameFeatures, timings: dict[str, float]) -> Relocalisation:
        """The frame's pose from the first candidate keyframe that confirms one; stage milliseconds
        (``relocalise_candidates``, ``relocalise_pose``) are added to ``timings``."""
        nothing = np.full(len(features), -1, np.int64)
        with stage_timer(timings, "relocalise_candidates"):
            candidates = tuple(self.candidates(features))
        if not candidates:
            return Relocalisation(None, nothing, "no_candidates", candidates)
        reason = "too_few_matches"
        with stage_timer(timings, "relocalise_pose"):
            for keyframe_id in candidates:
                found = self._try(keyframe_id, features)
                if found is None:
                    continue
                reason = "not_confirmed"
                T, point_ids = found
                inliers = int(np.count_nonzero(point_ids >= 0))
                if inliers >= self.settings.reloc_min_inliers:
                    return Relocalisation(T, point_ids, "", candidates, keyframe_id, inliers)
        return Relocalisation(None, nothing, reason, candidates)

    def _observed(self, keyframe_id: int) -> tuple[PointArrays, np.ndarray, PointArrays] | None:
        """The points keyframe ``keyframe_id`` observes, their keypoints' angles there (P,) degrees,
        and the points of its local map; None when it is gone."""
        with self.map.lock:
            keyframe = self.map.keyframes.get(keyframe_id)
            if keyframe is None:
                return None
            indices = np.flatnonzero(keyframe.point_ids >= 0)
            own = self.map.arrays(keyframe.point_ids[indices])
            angles = keyframe.features.angles[indices[np.isin(keyframe.point_ids[indices], own.ids)]]
            group = [keyframe_id] + self.covisibility.covisible(keyframe_id, COVISIBLE_OF_CANDIDATE)
            return own, angles, self.map.arrays(self.map.points_of(group))

    def _try(self, keyframe_id: int, features: FrameFeatures) -> tuple[np.ndarray, np.ndarray] | None:
        """PnP on descriptor matches with the points candidate ``keyframe_id`` observes, then the
        confirming projection search of its local map; the pose and (N,) point id per keypoint, or
        None without a PnP pose."""
        s = self.settings
        observed = self._observed(keyframe_id)
        if observed is None:
            return None
        own, angles, points = observed
        rows, keypoints = match_descriptors(own.descriptors, features.descriptors, s.match_max_distance,
                                            s.match_ratio)
        consistent = rotation_consistent(angles[rows], features.angles[keypoints])
        rows, keypoints = rows[consistent], keypoints[consistent]
        solved = solve_pnp(self.K, s, own.positions[rows], features, keypoints)
        if solved is None:
            return None
        refined, used = solved
        found = own.ids[rows[used][refined.inliers]]
        keypoints = keypoints[used][refined.inliers]
        rows = np.searchsorted(points.ids, found)
        available = np.ones(len(features), bool)
        available[keypoints] = False
        projected = project_points(points, refined.T_camera_world, self.K, self.size, self.map.scale_factor,
                                   self.map.levels)
        unmatched = ~np.isin(projected.rows, rows)
        searched = Projected(projected.rows[unmatched], projected.pixels[unmatched], projected.levels[unmatched],
                             projected.view_cos[unmatched])
        more_rows, more_keypoints = search_projected(points, searched, features, available, s.reloc_window_px,
                                                     self.map.scale_factor, s.projection_max_distance,
                                                     s.local_ratio)
        rows, keypoints = np.r_[rows, more_rows], np.r_[keypoints, more_keypoints]
        final = refine_pose(self.K, refined.T_camera_world, points.positions[rows], features.pixels[keypoints],
                            features.sigmas[keypoints])
        point_ids = np.full(len(features), -1, np.int64)
        point_ids[keypoints[final.inliers]] = points.ids[rows[final.inliers]]
        return final.T_camera_world, point_ids
