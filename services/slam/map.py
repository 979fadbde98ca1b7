"""The SLAM map: keyframes, map points, the observations linking them and the covisibility they imply.

World = the first keyframe's camera frame (OpenCV camera frame: x right, y down, z forward), in the
map's arbitrary monocular units. A keyframe holds its pose ``T_camera_world`` (4, 4) and its
features (``features.FrameFeatures``: undistorted pixels, levels, descriptors), with the id of
the map point each keypoint observes (-1 for none). A map point holds its position (3,) world, the
keyframes observing it (keyframe id -> keypoint index), a representative descriptor (the
observation's descriptor with the least median distance to the others), its mean viewing
direction and the range of distances at which ORB's pyramid can find it again, and two counters:
``visible`` (frames whose view it fell in) and ``found`` (frames that matched it).

Two keyframes are covisible when they observe common points; the weight is how many.

The map is shared by the tracker (reads) and the mapper (writes): every method takes ``lock``,
an ``RLock``; readers get copies, never live arrays. ``revision`` grows on every change.
"""

from __future__ import annotations

import threading
from collections import Counter
from dataclasses import dataclass, field

import numpy as np

from services.slam.features import FrameFeatures
from services.slam.matching import hamming_matrix

__all__ = ["Keyframe", "MapPoint", "SlamMap", "PointArrays"]

NEIGHBOURS_OF = 5
"""A local map adds the covisible neighbours of this many of its keyframes (those sharing most points)."""


@dataclass
class Keyframe:
    """``id``; ``stamp_ns``; ``T_camera_world`` (4, 4) float64; ``features`` of N keypoints;
    ``point_ids`` (N,) int64, the map point of each keypoint or -1."""

    id: int
    stamp_ns: int
    T_camera_world: np.ndarray
    features: FrameFeatures
    point_ids: np.ndarray

    centre: np.ndarray = field(init=False)
    """(3,) the camera centre, world frame (kept up to date by ``set_pose``)."""

    def __post_init__(self) -> None:
        self.set_pose(self.T_camera_world)

    def set_pose(self, T_camera_world: np.ndarray) -> None:
        self.T_camera_world = np.array(T_camera_world, np.float64)
        self.centre = -self.T_camera_world[:3, :3].T @ self.T_camera_world[:3, 3]


@dataclass
class MapPoint:
    """``position`` (3,) world; ``observations`` keyframe id -> keypoint index; ``first_keyframe`` the
    keyframe it was made in; ``descriptor`` (32,) uint8; ``normal`` (3,) unit mean viewing direction
    (from the cameras to the point); ``min_distance``, ``max_distance``: the distances from a camera
    at which ORB's pyramid can find it; ``visible``, ``found``: counters of tracked frames."""

    id: int
    position: np.ndarray
    observations: dict[int, int]
    first_keyframe: int
    descriptor: np.ndarray = field(default_factory=lambda: np.zeros(32, np.uint8))
    normal: np.ndarray = field(default_factory=lambda: np.zeros(3))
    min_distance: float = 0.0
    max_distance: float = np.inf
    visible: int = 1
    found: int = 1


@dataclass(frozen=True)
class PointArrays:
    """Copies of P map points' data: ``ids`` (P,) int64, ``positions`` (P, 3) world, ``descriptors``
    (P, 32) uint8, ``normals`` (P, 3), ``min_distances`` and ``max_distances`` (P,)."""

    ids: np.ndarray
    positions: np.ndarray
    descriptors: np.ndarray
    normals: np.ndarray
    min_distances: np.ndarray
    max_distances: np.ndarray

    def __len__(self) -> int:
        return len(self.ids)


class SlamMap:
    """Keyframes and map points of one camera whose ORB pyramid has ``levels`` levels, each
    ``scale_factor`` smaller than the one before."""

    def __init__(self, scale_factor: float, levels: int):
        self.scale_factor = scale_factor
        self.levels = levels
        self.lock = threading.RLock()
        self.keyframes: dict[int, Keyframe] = {}
        self.points: dict[int, MapPoint] = {}
        self.revision = 0
        self._next_keyframe = 0
        self._next_point = 0
        self._covisibility: dict[int, Counter[int]] = {}
        self._covisibility_revision = -1

    def clear(self) -> None:
        """Forget every keyframe and point."""
        with self.lock:
            self.keyframes.clear()
            self.points.clear()
            self.revision += 1

    def add_keyframe(self, stamp_ns: int, T_camera_world: np.ndarray, features: FrameFeatures,
                     point_ids: np.ndarray) -> Keyframe:
        """A new keyframe; each keypoint ``i`` with ``point_ids[i] >= 0`` (an existing point) becomes an
        observation of that point (ids of points since removed are dropped)."""
        with self.lock:
            keyframe = Keyframe(self._next_keyframe, stamp_ns, np.array(T_camera_world, np.float64), features,
                                np.full(len(features), -1, np.int64))
            self._next_keyframe += 1
            self.keyframes[keyframe.id] = keyframe
            for index in np.flatnonzero(point_ids >= 0):
                point = self.points.get(int(point_ids[index]))
                if point is not None and keyframe.id not in point.observations:
                    self._observe(point, keyframe, int(index))
            for point_id in set(keyframe.point_ids[keyframe.point_ids >= 0].tolist()):
                self.update_point(point_id)
            self.revision += 1
            return keyframe

    def add_point(self, position: np.ndarray, observations: dict[int, int]) -> int:
        """A new point at ``position`` (3,) world, seen by keyframe id -> keypoint index (at least one)."""
        with self.lock:
            point = MapPoint(self._next_point, np.array(position, np.float64), {}, min(observations))
            self._next_point += 1
            self.points[point.id] = point
            for keyframe_id, index in observations.items():
                self._observe(point, self.keyframes[keyframe_id], index)
            self.update_point(point.id)
            self.revision += 1
            return point.id

    def add_observation(self, point_id: int, keyframe_id: int, index: int) -> None:
        """Keypoint ``index`` of keyframe ``keyframe_id`` observes point ``point_id``."""
        with self.lock:
            point, keyframe = self.points[point_id], self.keyframes[keyframe_id]
            if keyframe_id in point.observations or keyframe.point_ids[index] >= 0:
                return
            self._observe(point, keyframe, index)
            self.update_point(point_id)
            self.revision += 1

    def _observe(self, point: MapPoint, keyframe: Keyframe, index: int) -> None:
        point.observations[keyframe.id] = index
        keyframe.point_ids[index] = point.id

    def remove_observation(self, point_id: int, keyframe_id: int) -> None:
        """Drop one observation; a point left with fewer than two is removed."""
        with self.lock:
            point = self.points.get(point_id)
            if point is None or keyframe_id not in point.observations:
                return
            index = point.observations.pop(keyframe_id)
            self.keyframes[keyframe_id].point_ids[index] = -1
            if len(point.observations) < 2:
                self.remove_point(point_id)
            else:
                self.update_point(point_id)
            self.revision += 1

    def remove_point(self, point_id: int) -> None:
        """Remove a point and every observation of it."""
        with self.lock:
            point = self.points.pop(point_id, None)
            if point is None:
                return
            for keyframe_id, index in point.observations.items():
                self.keyframes[keyframe_id].point_ids[index] = -1
            self.revision += 1

    def merge_points(self, kept_id: int, merged_id: int) -> None:
        """Fuse duplicate ``merged_id`` into ``kept_id``: its observations (in keyframes not already
        observing ``kept_id``) and counters move over, then it is removed."""
        with self.lock:
            kept, merged = self.points.get(kept_id), self.points.get(merged_id)
            if kept is None or merged is None or kept_id == merged_id:
                return
            moved = {k: i for k, i in merged.observations.items() if k not in kept.observations}
            self.remove_point(merged_id)
            for keyframe_id, index in moved.items():
                self._observe(kept, self.keyframes[keyframe_id], index)
            kept.visible += merged.visible
            kept.found += merged.found
            self.update_point(kept_id)

    def update_point(self, point_id: int) -> None:
        """Recompute a point's representative descriptor, viewing direction and distance range."""
        with self.lock:
            point = self.points[point_id]
            keyframes = [self.keyframes[k] for k in point.observations]
            descriptors = np.array([k.features.descriptors[i] for k, i in zip(keyframes, point.observations.values(),
                                                                              strict=True)])
            if len(descriptors) > 2:
                distances = np.sort(hamming_matrix(descriptors, descriptors), axis=1)
                descriptors = descriptors[[int(np.argmin(distances[:, (len(descriptors) - 1) // 2]))]]
            point.descriptor = descriptors[0].copy()
            rays = point.position - np.array([k.centre for k in keyframes])
            lengths = np.linalg.norm(rays, axis=1)
            mean = np.sum(rays / np.maximum(lengths, 1e-12)[:, None], axis=0)
            point.normal = mean / max(float(np.linalg.norm(mean)), 1e-12)
            first = self.keyframes.get(point.first_keyframe, keyframes[0])
            index = point.observations.get(first.id, point.observations[keyframes[0].id])
            distance = float(np.linalg.norm(point.position - first.centre))
            level = int(first.features.levels[index])
            point.max_distance = distance * self.scale_factor ** level
            point.min_distance = point.max_distance / self.scale_factor ** (self.levels - 1)

    def set_pose(self, keyframe_id: int, T_camera_world: np.ndarray) -> None:
        with self.lock:
            self.keyframes[keyframe_id].set_pose(T_camera_world)
            self.revision += 1

    def set_position(self, point_id: int, position: np.ndarray) -> None:
        with self.lock:
            if point_id in self.points:
                self.points[point_id].position = np.array(position, np.float64)
                self.revision += 1

    def count_visible(self, point_ids: np.ndarray, found: np.ndarray | None = None) -> None:
        """Add one to ``visible`` of each point of ``point_ids`` (P,), and to ``found`` where ``found`` (P,) bool."""
        with self.lock:
            for k, point_id in enumerate(point_ids.tolist()):
                point = self.points.get(point_id)
                if point is not None:
                    point.visible += 1
                    point.found += int(found is not None and found[k])

    def covisibility(self, keyframe_id: int) -> Counter[int]:
        """Other keyframe id -> how many of ``keyframe_id``'s points it observes too (remembered until
        the map's next change)."""
        with self.lock:
            if self._covisibility_revision != self.revision:
                self._covisibility.clear()
                self._covisibility_revision = self.revision
            if keyframe_id not in self._covisibility:
                self._covisibility[keyframe_id] = self._count_covisible(keyframe_id)
            return Counter(self._covisibility[keyframe_id])

    def _count_covisible(self, keyframe_id: int) -> Counter[int]:
        with self.lock:
            counts: Counter[int] = Counter()
            for point_id in self.keyframes[keyframe_id].point_ids[self.keyframes[keyframe_id].point_ids >= 0]:
                counts.update(self.points[int(point_id)].observations.keys())
            counts.pop(keyframe_id, None)
            return counts

    def covisible(self, keyframe_id: int, count: int, least: int = 1) -> list[int]:
        """Up to ``count`` keyframes sharing at least ``least`` points with ``keyframe_id``, most shared first."""
        return [k for k, n in self.covisibility(keyframe_id).most_common(count) if n >= least]

    def observers(self, point_ids: np.ndarray) -> Counter[int]:
        """Keyframe id -> how many of the points ``point_ids`` (P,) it observes."""
        with self.lock:
            counts: Counter[int] = Counter()
            for point_id in point_ids.tolist():
                point = self.points.get(point_id)
                if point is not None:
                    counts.update(point.observations.keys())
            return counts

    def local_keyframes(self, point_ids: np.ndarray, count: int) -> list[int]:
        """The keyframes of a frame's local map: those observing its matched ``point_ids``, most shared
        first, then the best covisible neighbours of those; at most ``count``."""
        with self.lock:
            direct = [k for k, _ in self.observers(point_ids).most_common(count)]
            chosen = list(direct)
            for keyframe_id in direct[:NEIGHBOURS_OF]:
                if len(chosen) >= count:
                    break
                chosen.extend(k for k in self.covisible(keyframe_id, 10) if k not in chosen)
            return chosen[:count]

    def point_ids(self) -> np.ndarray:
        """(P,) int64 sorted ids of every point."""
        with self.lock:
            return np.array(sorted(self.points), np.int64)

    def points_of(self, keyframe_ids: list[int]) -> np.ndarray:
        """(P,) int64 sorted ids of the points the keyframes observe."""
        with self.lock:
            ids = [self.keyframes[k].point_ids for k in keyframe_ids if k in self.keyframes]
            everything = np.concatenate(ids) if ids else np.zeros(0, np.int64)
            return np.unique(everything[everything >= 0])

    def arrays(self, point_ids: np.ndarray) -> PointArrays:
        """Copies of the data of the points ``point_ids`` that still exist."""
        with self.lock:
            points = [self.points[i] for i in point_ids.tolist() if i in self.points]
            return PointArrays(ids=np.array([p.id for p in points], np.int64).reshape(-1),
                               positions=np.array([p.position for p in points], np.float64).reshape(-1, 3),
                               descriptors=np.array([p.descriptor for p in points], np.uint8).reshape(-1, 32),
                               normals=np.array([p.normal for p in points], np.float64).reshape(-1, 3),
                               min_distances=np.array([p.min_distance for p in points], np.float64),
                               max_distances=np.array([p.max_distance for p in points], np.float64))

    def cull_points(self, newest_keyframe: int, min_found_ratio: float, min_observations: int,
                    probation: int) -> int:
        """Remove the points made within the last ``probation`` keyframes before ``newest_keyframe`` that
        failed: found in under ``min_found_ratio`` of the frames they were visible in, or, two
        keyframes or more after their making, observed by fewer than ``min_observations`` keyframes.
        Returns how many were removed."""
        with self.lock:
            doomed = [p.id for p in self.points.values()
                      if newest_keyframe - p.first_keyframe <= probation
                      and (p.found < min_found_ratio * p.visible
                           or (newest_keyframe - p.first_keyframe >= 2 and len(p.observations) < min_observations))]
            for point_id in doomed:
                self.remove_point(point_id)
            return len(doomed)
