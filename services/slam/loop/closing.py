"""Loop closing: a keyframe that sees again a place mapped long before pulls the map's drift out.

For each new keyframe, after its local mapping (ORB-SLAM's loop closing, run by the mapper):

1. **Detect.** Earlier keyframes that look like it (``places.PlaceIndex``: hashed ORB words of every
   keyframe, indexed as they come), its covisible keyframes left out. A candidate is kept only once it
   was found for ``loop_consistency`` keyframes in a row besides this one: each candidate's group (it and
   its ``GROUP_NEIGHBOURS`` best covisible keyframes) must share a keyframe with a group kept for the
   keyframe before.
2. **Verify.** The keyframe's map points are matched by descriptor with the points of the candidate's
   group; a similarity ``S`` (``sim3.fit_sim3``) taking the keyframe's (drifted) points onto the group's
   (RANSAC on three matches, each hypothesis scored by the reprojection of the group's points into the
   keyframe under the corrected pose, ``CHI2_TWO_DOF`` of their level's sigma, then Umeyama on the
   inliers); the group's points are then searched for around their projections in the keyframe
   (``projection.search_projected``) and the loop is accepted with ``loop_min_inliers`` matches
   within the chi-square bound in all.
3. **Correct.** The keyframe and its covisible keyframes (the neighbourhood, sharing at least
   ``NEIGHBOURHOOD_SHARED`` points with it) are moved by ``S`` (their pose ``T_camera_world S^-1``, a
   similarity, kept rigid with its scale folded into the points) and so are the points they observe
   (``S x``). The group's points are fused into the neighbourhood's keyframes: the matches found in step 2,
   then a projection search in each of them (a keypoint with a point already: the two are merged, the
   group's kept; one without: it gains the observation).
4. **Pose graph.** Every keyframe a node in Sim(3) (``pose_graph``), edges: the spanning tree (each
   keyframe to its earlier keyframe sharing most points), strong covisibility (at least
   ``STRONG_COVISIBILITY`` points, before the fusion), both measured on the poses before the correction,
   and the loop edges (keyframes of the neighbourhood to those they share points with only after the
   fusion) measured on the corrected ones. The loop's keyframe and the map's first keyframe are fixed.
   Each point then follows its reference keyframe (the neighbourhood keyframe that moved it, else the
   first of its observers): ``x <- S_r_after^-1 S_r_before x``.
5. **Global bundle adjustment** of the whole map (the caller's, ``LocalMapper.adjust`` with every
   keyframe: the first fixed, scale held).

Everything is written through ``MapDatabase``'s methods, so a copy of the map in another process gets the
corrected map as it gets local mapping's changes (``map.sync``). Frames: ``T_camera_world`` (4, 4) rigid,
world = the first keyframe's camera frame; similarities are (4, 4) as in ``sim3``.
"""

from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from services.geometry.se3 import transform_points
from services.slam.features import FrameFeatures
from services.slam.loop.places import PlaceIndex
from services.slam.loop.pose_graph import Edge, optimise_pose_graph
from services.slam.loop.sim3 import decompose, fit_sim3
from services.slam.map.covisibility import CovisibilityGraph
from services.slam.map.database import MapDatabase
from services.slam.map.map_point import PointArrays
from services.slam.matching import match_descriptors
from services.slam.optimisation import reprojection_errors
from services.slam.projection import project_points, search_projected
from services.slam.settings import SlamSettings
from services.slam.timing import stage_timer

__all__ = ["LoopCloser", "LoopClosure", "rigid"]

logger = logging.getLogger(__name__)

CHI2_TWO_DOF = 5.991
MIN_KEYFRAMES = 10
"""No loop is looked for in a map of fewer keyframes, nor within this many keyframes of the last loop."""
GROUP_NEIGHBOURS = 10
NEIGHBOURHOOD_SHARED = 15
STRONG_COVISIBILITY = 100
MATCH_RATIO = 0.75
SEARCH_WINDOW_PX = 10.0
"""Search window of the group's points in the keyframe (step 2), px per level scale."""
FUSE_WINDOW_PX = 4.0
"""Search window of the group's points in the neighbourhood's keyframes (step 3), px per level scale."""
RANSAC_ITERATIONS = 300
GLOBAL_BA_ITERATIONS = 20


@dataclass(frozen=True)
class LoopClosure:
    """A loop closed: ``keyframe_id`` the keyframe that saw the place again, ``loop_keyframe_id`` the
    earlier keyframe it matched; ``S_loop_current`` (4, 4) the similarity that took the keyframe's
    points onto the loop's (world to world), its ``scale``; ``inliers`` matches that accepted it;
    ``fused`` observations merged or added; ``moved_keyframes`` keyframes corrected first
    (the neighbourhood); ``stages`` ms per step."""

    keyframe_id: int
    loop_keyframe_id: int
    S_loop_current: np.ndarray
    scale: float
    inliers: int
    fused: int
    moved_keyframes: int
    stages: dict[str, float] = field(default_factory=dict)


def rigid(S_camera_world: np.ndarray) -> np.ndarray:
    """(4, 4) the rigid pose of a camera whose similarity pose is ``S_camera_world`` (4, 4): the same
    rotation and centre (its scale belongs to the points)."""
    scale, R, t = decompose(S_camera_world)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t / scale
    return T


@dataclass(frozen=True)
class _Match:
    """A verified loop: ``S`` (4, 4) world to world; ``keypoints`` (M,) of the keyframe matched to the
    group's points ``point_ids`` (M,); ``group`` the candidate's group of keyframes."""

    S: np.ndarray
    keypoints: np.ndarray
    point_ids: np.ndarray
    group: list[int]


class LoopCloser:
    """Closes loops in ``slam_map`` (a camera of intrinsics ``K`` (3, 3), image ``size`` (w, h));
    ``adjust(keyframe_ids, iterations)`` bundle adjusts the map's keyframes given (the first fixed).
    ``closures``: every loop closed, oldest first."""

    def __init__(self, slam_map: MapDatabase, K: np.ndarray, size: tuple[int, int], settings: SlamSettings,
                 adjust: Callable[[list[int], int], None]):
        self.map = slam_map
        self.covisibility = CovisibilityGraph(slam_map)
        self.K = np.asarray(K, np.float64)
        self.size = size
        self.settings = settings
        self.adjust = adjust
        self.places = PlaceIndex()
        self.closures: list[LoopClosure] = []
        self._groups: list[tuple[set[int], int]] = []
        """The candidate groups kept for the last keyframe, with how many keyframes in a row found them."""
        self._last_loop = -1

    def process(self, keyframe_id: int) -> LoopClosure | None:
        """Look for a loop at keyframe ``keyframe_id`` and close it (module docstring); the closure or None."""
        stages: dict[str, float] = {}
        with stage_timer(stages, "detect"):
            with self.map.lock:
                keyframe = self.map.keyframes.get(keyframe_id)
                missing = {k: f.features.descriptors for k, f in self.map.keyframes.items()
                           if k not in self.places and k != keyframe_id}
                count = len(self.map.keyframes)
            if keyframe is None:
                return None
            for other, descriptors in sorted(missing.items()):
                self.places.add(other, descriptors)
            candidates = []
            if count >= MIN_KEYFRAMES and (self._last_loop < 0 or keyframe_id - self._last_loop >= MIN_KEYFRAMES):
                candidates = self._consistent(keyframe_id, keyframe.features)
            self.places.add(keyframe_id, keyframe.features.descriptors)
        for candidate in candidates:
            with stage_timer(stages, "verify"):
                match = self._verify(keyframe_id, candidate)
            if match is not None:
                closure = self._close(keyframe_id, candidate, match, stages)
                self._groups.clear()
                self._last_loop = keyframe_id
                self.closures.append(closure)
                logger.info("loop closed: keyframe %d saw keyframe %d's place again (scale %.3f, %d matches, "
                            "%d fused) in %.0f ms", keyframe_id, candidate, closure.scale, closure.inliers,
                            closure.fused, sum(stages.values()))
                return closure
        return None

    def _group(self, keyframe_id: int) -> set[int]:
        return {keyframe_id, *self.covisibility.covisible(keyframe_id, GROUP_NEIGHBOURS)}

    def _consistent(self, keyframe_id: int, features: FrameFeatures) -> list[int]:
        """The place index's candidates whose groups were found for ``loop_consistency`` keyframes before
        this one in a row (the groups kept for the next keyframe)."""
        neighbours = set(self.covisibility.covisibility(keyframe_id))
        candidates = self.places.loop_candidates(keyframe_id, features.descriptors, neighbours,
                                                 lambda k: self.covisibility.covisible(k, GROUP_NEIGHBOURS))
        kept: list[tuple[set[int], int]] = []
        accepted = []
        for candidate in candidates:
            group = self._group(candidate)
            runs = [count + 1 for previous, count in self._groups if previous & group]
            run = max(runs, default=0)
            kept.append((group, run))
            if run >= self.settings.loop_consistency:
                accepted.append(candidate)
        self._groups = kept
        return accepted

    def _points_seen(self, keyframe_id: int) -> tuple[np.ndarray, PointArrays, np.ndarray]:
        """``(keypoints (M,), their points, T_camera_world (4, 4))`` of keyframe ``keyframe_id``."""
        with self.map.lock:
            keyframe = self.map.keyframes[keyframe_id]
            keypoints = np.flatnonzero(keyframe.point_ids >= 0)
            points = self.map.arrays(keyframe.point_ids[keypoints])
            keypoints = keypoints[np.isin(keyframe.point_ids[keypoints], points.ids)]
            return keypoints, points, keyframe.T_camera_world.copy()

    def _verify(self, keyframe_id: int, candidate: int) -> _Match | None:
        """Step 2: the similarity and matches of the loop between keyframe ``keyframe_id`` and the group of
        ``candidate``, or None when too few matches agree."""
        s = self.settings
        with self.map.lock:
            if candidate not in self.map.keyframes:
                return None
            features = self.map.keyframes[keyframe_id].features
            near = set(self.covisibility.covisibility(keyframe_id)) | {keyframe_id}
            group = [k for k in sorted(self._group(candidate)) if k not in near]
            seen = self.map.keyframes[keyframe_id].point_ids
            group_points = self.map.arrays(np.setdiff1d(self.map.points_of(group), seen))
        keypoints, own, T = self._points_seen(keyframe_id)
        if len(group_points) < s.loop_min_inliers or len(own) < s.loop_min_inliers:
            return None
        rows, columns = match_descriptors(group_points.descriptors, features.descriptors[keypoints],
                                          s.match_max_distance, MATCH_RATIO)
        if len(rows) < s.pnp_min_inliers:
            return None
        pixels, sigmas = features.pixels[keypoints[columns]], features.sigmas[keypoints[columns]]
        target = group_points.positions[rows]

        def chi2(S: np.ndarray) -> np.ndarray:
            return self._chi2(T @ np.linalg.inv(S), target, pixels, sigmas)

        fit = fit_sim3(own.positions[columns], target, CHI2_TWO_DOF, chi2, RANSAC_ITERATIONS, s.pnp_min_inliers)
        if fit is None:
            return None
        T_corrected = rigid(T @ np.linalg.inv(fit.S_target_source))
        matched_rows, matched_keypoints = rows[fit.inliers], keypoints[columns[fit.inliers]]
        available = np.ones(len(features), bool)
        available[matched_keypoints] = False
        rest = np.setdiff1d(np.arange(len(group_points)), matched_rows)
        others = _subset(group_points, rest)
        projected = project_points(others, T_corrected, self.K, self.size, self.map.scale_factor, self.map.levels)
        more_rows, more_keypoints = search_projected(others, projected, features, available, SEARCH_WINDOW_PX,
                                                     self.map.scale_factor, s.projection_max_distance, MATCH_RATIO)
        all_rows = np.r_[matched_rows, rest[more_rows]]
        all_keypoints = np.r_[matched_keypoints, more_keypoints]
        good = self._chi2(T_corrected, group_points.positions[all_rows], features.pixels[all_keypoints],
                          features.sigmas[all_keypoints]) <= CHI2_TWO_DOF
        if np.count_nonzero(good) < s.loop_min_inliers:
            return None
        return _Match(fit.S_target_source, all_keypoints[good], group_points.ids[all_rows[good]], group)

    def _chi2(self, S_camera_world: np.ndarray, points: np.ndarray, pixels: np.ndarray,
              sigmas: np.ndarray) -> np.ndarray:
        """(N,) squared reprojection errors over sigma^2 of (N, 3) world ``points`` seen at (N, 2)
        ``pixels`` by a camera of similarity pose ``S_camera_world`` (infinite behind it)."""
        return (reprojection_errors(self.K, S_camera_world, points, pixels) / sigmas) ** 2

    def _close(self, keyframe_id: int, loop_id: int, match: _Match, stages: dict[str, float]) -> LoopClosure:
        """Steps 3 to 5."""
        with stage_timer(stages, "correct"):
            with self.map.lock:
                before = {k: f.T_camera_world.copy() for k, f in self.map.keyframes.items()}
                neighbourhood = [keyframe_id] + self.covisibility.covisible(keyframe_id, len(before),
                                                                            NEIGHBOURHOOD_SHARED)
                covisible_before = {k: self.covisibility.covisibility(k) for k in before}
            S_inverse = np.linalg.inv(match.S)
            corrected = {k: before[k] @ S_inverse for k in neighbourhood}
            reference = self._move_neighbourhood(neighbourhood, corrected, match.S)
        with stage_timer(stages, "fuse"):
            fused = self._fuse(keyframe_id, neighbourhood, match)
        with stage_timer(stages, "pose_graph"):
            start = {k: corrected.get(k, T) for k, T in before.items()}
            edges = self._edges(before, start, covisible_before, set(neighbourhood))
            first = min(before)
            result = optimise_pose_graph(start, edges, {first, loop_id})
            self._apply(start, result.poses, reference)
        with stage_timer(stages, "global_bundle_adjustment"):
            with self.map.lock:
                every = sorted(self.map.keyframes)
            self.adjust(every, GLOBAL_BA_ITERATIONS)
        scale = decompose(match.S)[0]
        return LoopClosure(keyframe_id, loop_id, match.S, scale, len(match.keypoints), fused, len(neighbourhood),
                           stages)

    def _move_neighbourhood(self, neighbourhood: list[int], corrected: dict[int, np.ndarray],
                            S: np.ndarray) -> dict[int, int]:
        """The neighbourhood's keyframes to their corrected poses and their points by ``S``; point id -> the
        neighbourhood keyframe that moved it."""
        reference: dict[int, int] = {}
        with self.map.lock:
            for k in neighbourhood:
                self.map.set_pose(k, rigid(corrected[k]))
                for point_id in self.map.points_of([k]).tolist():
                    if point_id not in reference:
                        reference[point_id] = k
            ids = np.fromiter(reference, np.int64, len(reference))
            positions = transform_points(S, self.map.positions(ids))
            for point_id, position in zip(ids.tolist(), positions, strict=True):
                self.map.set_position(point_id, position)
        return reference

    def _fuse(self, keyframe_id: int, neighbourhood: list[int], match: _Match) -> int:
        """Step 3's fusion; how many observations were merged or added."""
        changed = self._join(keyframe_id, match.keypoints, match.point_ids)
        with self.map.lock:
            group_ids = self.map.points_of(match.group)
        for target in neighbourhood:
            with self.map.lock:
                keyframe = self.map.keyframes[target]
                T, features, owners = keyframe.T_camera_world.copy(), keyframe.features, keyframe.point_ids.copy()
            points = self.map.arrays(group_ids[~np.isin(group_ids, owners)])
            projected = project_points(points, T, self.K, self.size, self.map.scale_factor, self.map.levels)
            rows, keypoints = search_projected(points, projected, features, np.ones(len(features), bool),
                                               FUSE_WINDOW_PX, self.map.scale_factor,
                                               self.settings.triangulation_max_distance, 1.0)
            changed += self._join(target, keypoints, points.ids[rows])
        self.map.refresh_points(group_ids)
        return changed

    def _join(self, keyframe_id: int, keypoints: np.ndarray, point_ids: np.ndarray) -> int:
        """Keypoints ``keypoints`` (M,) of keyframe ``keyframe_id`` see the points ``point_ids`` (M,): a
        keypoint's own point merged into it, or the observation added; how many changed."""
        changed = 0
        with self.map.lock:
            keyframe = self.map.keyframes[keyframe_id]
            for index, point_id in zip(keypoints.tolist(), point_ids.tolist(), strict=True):
                point = self.map.points.get(point_id)
                if point is None or keyframe_id in point.observations:
                    continue
                owner = int(keyframe.point_ids[index])
                if owner < 0:
                    self.map.add_observation(point_id, keyframe_id, index, refresh=False)
                elif owner != point_id and owner in self.map.points:
                    self.map.merge_points(point_id, owner, refresh=False)
                else:
                    continue
                changed += 1
        return changed

    def _edges(self, before: dict[int, np.ndarray], start: dict[int, np.ndarray],
               covisible_before: dict[int, Counter[int]], neighbourhood: set[int]) -> list[Edge]:
        """Step 4's edges: spanning tree and strong covisibility measured on the poses ``before`` the
        correction, loop edges on the ``start`` (corrected) ones."""
        edges: list[Edge] = []
        seen: set[tuple[int, int]] = set()

        def add(i: int, j: int, poses: dict[int, np.ndarray]) -> None:
            key = (min(i, j), max(i, j))
            if i != j and key not in seen and i in poses and j in poses:
                seen.add(key)
                edges.append((i, j, poses[i] @ np.linalg.inv(poses[j])))

        ids = sorted(before)
        for k in ids[1:]:
            weights = covisible_before[k]
            earlier = {j: n for j, n in weights.items() if j < k}
            parent = max(earlier, key=lambda j: (earlier[j], j)) if earlier else max(j for j in ids if j < k)
            add(k, parent, before)
            for j, n in weights.items():
                if n >= STRONG_COVISIBILITY:
                    add(k, j, before)
        for k in sorted(neighbourhood):
            if k not in self.map.keyframes:
                continue
            for j in self.covisibility.covisibility(k):
                if j not in neighbourhood and j not in covisible_before[k]:
                    add(k, j, start)
        return edges

    def _apply(self, start: dict[int, np.ndarray], optimised: dict[int, np.ndarray],
               reference: dict[int, int]) -> None:
        """Every keyframe to its optimised pose, every point with its reference keyframe."""
        with self.map.lock:
            for k, S in optimised.items():
                if k in self.map.keyframes:
                    self.map.set_pose(k, rigid(S))
            ids = self.map.point_ids()
            positions = self.map.positions(ids)
            references = np.array([self._reference(point_id, reference) for point_id in ids.tolist()], np.int64)
            for r in np.unique(references).tolist():
                if r in optimised and r in start:
                    rows = np.flatnonzero(references == r)
                    moved = transform_points(np.linalg.inv(optimised[r]) @ start[r], positions[rows])
                    for point_id, position in zip(ids[rows].tolist(), moved, strict=True):
                        self.map.set_position(point_id, position)
        self.map.refresh_points(ids)

    def _reference(self, point_id: int, reference: dict[int, int]) -> int:
        """The keyframe point ``point_id`` moves with: the one that moved it in step 3 if it still observes
        it, else the one it was made in if it observes it still, else its first observer (map locked)."""
        point = self.map.points[point_id]
        r = reference.get(point_id)
        if r is not None and r in point.observations:
            return r
        return point.first_keyframe if point.first_keyframe in point.observations else min(point.observations)


def _subset(points: PointArrays, rows: np.ndarray) -> PointArrays:
    return PointArrays(points.ids[rows], points.positions[rows], points.descriptors[rows], points.normals[rows],
                       points.min_distances[rows], points.max_distances[rows])
