"""The map database: keyframes, map points and the observations linking them, kept consistent.

World = the first keyframe's camera frame (OpenCV camera frame: x right, y down, z forward), in the
map's arbitrary monocular units. A keyframe (``keyframe.Keyframe``) holds its pose
``T_camera_world`` (4, 4) and its features (``features.FrameFeatures``: undistorted pixels, levels,
descriptors), with the id of the map point each keypoint observes (-1 for none). A map point
(``map_point.MapPoint``) holds its position (3,) world, the keyframes observing it (keyframe id ->
keypoint index), its summary (``point_summary``: representative descriptor, mean viewing direction,
distance range) and two counters: ``visible`` (frames whose view it fell in) and ``found`` (frames
that matched it).

The database is shared by the tracker (reads) and the mapper (writes): every method takes ``lock``,
an ``RLock``; readers get copies, never live arrays. ``revision`` grows on every change of keyframes,
points or observations. The lock is held only while the dictionaries are read or changed: a point's
summary is computed from a snapshot of its observations outside the lock and written back under it
unless the point changed meanwhile (``refresh_points``, ``add_points``).

What a frame's tracking reads of many points (``arrays``, ``positions``) comes from ``table``
(``point_table``): a copy of the points' positions and summaries in arrays by point id, written by every
method here that changes them (and by ``sync`` when it replaces points).

While a copy of the map is kept in another process (``sync``), the database notes its changes in
``changes`` and the counters it adds in ``counts`` (``journal``); both are None otherwise.
"""

from __future__ import annotations

import threading

import numpy as np

from services.slam.features import FrameFeatures
from services.slam.map.journal import ChangeJournal, CountJournal
from services.slam.map.keyframe import Keyframe
from services.slam.map.map_point import MapPoint, PointArrays
from services.slam.map.point_summary import PointDraft, PointSummaries, summarise
from services.slam.map.point_table import PointTable

__all__ = ["MapDatabase"]


class MapDatabase:
    """Keyframes and map points of one camera whose ORB pyramid has ``levels`` levels, each
    ``scale_factor`` smaller than the one before."""

    def __init__(self, scale_factor: float, levels: int):
        self.scale_factor = scale_factor
        self.levels = levels
        self.lock = threading.RLock()
        self.keyframes: dict[int, Keyframe] = {}
        self.points: dict[int, MapPoint] = {}
        self.table = PointTable()
        """The points' positions and summaries as arrays by id (``point_table``), kept with ``points``."""
        self.revision = 0
        self.next_keyframe_id = 0
        """The id the next keyframe gets unless one is given."""
        self.next_point_id = 0
        """The id the next point gets."""
        self.replaced: dict[int, int] = {}
        """Merged point id -> the id of the point it was merged into (``resolve``)."""
        self.changes: ChangeJournal | None = None
        """The changes noted for a copy of the map (``sync.record_changes``), or None."""
        self.counts: CountJournal | None = None
        """The counters noted for a copy of the map (``sync.record_counts``), or None."""

    def resolve(self, point_ids: np.ndarray) -> np.ndarray:
        """(P,) int64: ``point_ids`` with each merged point's id replaced by the id of the point it lives
        on in (-1 stays -1), so that a keyframe made on a copy of the map before a merge keeps its
        observations."""
        with self.lock:
            if not self.replaced:
                return np.asarray(point_ids, np.int64).copy()
            resolved = []
            for point_id in np.asarray(point_ids, np.int64).tolist():
                for _ in range(len(self.replaced)):
                    if point_id not in self.replaced:
                        break
                    point_id = self.replaced[point_id]
                resolved.append(point_id)
            return np.array(resolved, np.int64)

    def clear(self) -> None:
        """Forget every keyframe and point."""
        with self.lock:
            self.keyframes.clear()
            self.points.clear()
            self.table.rebuild(())
            self.replaced.clear()
            if self.changes is not None:
                self.changes = ChangeJournal()
            self.revision += 1

    def add_keyframe(self, stamp_ns: int, T_camera_world: np.ndarray, features: FrameFeatures,
                     point_ids: np.ndarray, keyframe_id: int | None = None) -> Keyframe:
        """A new keyframe (its id ``keyframe_id``, as a copy of this map named it, or the next); each
        keypoint ``i`` with ``point_ids[i] >= 0`` (an existing point, or one merged into it since:
        ``resolve``) becomes an observation of that point (ids of points since removed are dropped)."""
        with self.lock:
            new_id = self.next_keyframe_id if keyframe_id is None else keyframe_id
            keyframe = Keyframe(new_id, stamp_ns, np.array(T_camera_world, np.float64), features,
                                np.full(len(features), -1, np.int64))
            self.next_keyframe_id = max(self.next_keyframe_id, new_id + 1)
            self.keyframes[keyframe.id] = keyframe
            if self.changes is not None:
                self.changes.keyframes.add(keyframe.id)
            indices = np.flatnonzero(point_ids >= 0)
            for index, point_id in zip(indices.tolist(), self.resolve(point_ids[indices]).tolist(), strict=True):
                point = self.points.get(point_id)
                if point is not None and keyframe.id not in point.observations:
                    self._observe(point, keyframe, index)
            self.revision += 1
        self.refresh_points(np.unique(keyframe.point_ids[keyframe.point_ids >= 0]))
        return keyframe

    def add_point(self, position: np.ndarray, observations: dict[int, int]) -> int:
        """A new point at ``position`` (3,) world, seen by keyframe id -> keypoint index (at least one)."""
        with self.lock:
            point = MapPoint(self.next_point_id, np.array(position, np.float64), {}, min(observations))
            self.next_point_id += 1
            self.points[point.id] = point
            for keyframe_id, index in observations.items():
                self._observe(point, self.keyframes[keyframe_id], index)
            self.update_point(point.id)
            self.revision += 1
            return point.id

    def add_points(self, positions: np.ndarray, observations: list[dict[int, int]]) -> list[int]:
        """New points at (N, 3) ``positions`` world, each seen by keyframe id -> keypoint index; a point
        whose keypoints got another point meanwhile (or whose keyframe is gone) is not added. Their
        summaries are computed before the lock is taken, which is held once, briefly. Returns the new ids."""
        with self.lock:
            keyframes = [{k: self.keyframes[k] for k in seen} if all(k in self.keyframes for k in seen) else None
                         for seen in observations]
        candidates = [(row, found) for row, found in enumerate(keyframes) if found is not None]
        drafts = [PointDraft(positions[row], [(found[k], i) for k, i in observations[row].items()],
                             (found[min(found)], observations[row][min(found)])) for row, found in candidates]
        summaries = summarise(drafts, self.scale_factor, self.levels) if drafts else None
        made: list[int] = []
        with self.lock:
            for n, (row, found) in enumerate(candidates):
                if any(self.keyframes.get(k) is not found[k] or found[k].point_ids[i] >= 0
                       for k, i in observations[row].items()):
                    continue
                point = MapPoint(self.next_point_id, np.array(positions[row], np.float64), {}, min(found))
                self.next_point_id += 1
                self.points[point.id] = point
                for keyframe_id, index in observations[row].items():
                    self._observe(point, found[keyframe_id], index)
                assert summaries is not None
                self._set_summary(point, summaries, n)
                made.append(point.id)
            self.revision += 1
        return made

    def add_observation(self, point_id: int, keyframe_id: int, index: int, refresh: bool = True) -> None:
        """Keypoint ``index`` of keyframe ``keyframe_id`` observes point ``point_id``; ``refresh=False``
        leaves the point's summary to the caller's ``refresh_points``."""
        with self.lock:
            point, keyframe = self.points[point_id], self.keyframes[keyframe_id]
            if keyframe_id in point.observations or keyframe.point_ids[index] >= 0:
                return
            self._observe(point, keyframe, index)
            if refresh:
                self.update_point(point_id)
            self.revision += 1

    def _observe(self, point: MapPoint, keyframe: Keyframe, index: int) -> None:
        point.observations[keyframe.id] = index
        keyframe.point_ids[index] = point.id
        if self.changes is not None:
            self.changes.point(point.id)
            self.changes.keyframes.add(keyframe.id)

    def remove_observation(self, point_id: int, keyframe_id: int, refresh: bool = True) -> None:
        """Drop one observation; a point left with fewer than two is removed (``refresh`` as in
        ``add_observation``)."""
        with self.lock:
            point = self.points.get(point_id)
            if point is None or keyframe_id not in point.observations:
                return
            index = point.observations.pop(keyframe_id)
            self.keyframes[keyframe_id].point_ids[index] = -1
            if self.changes is not None:
                self.changes.point(point_id)
                self.changes.keyframes.add(keyframe_id)
            if len(point.observations) < 2:
                self.remove_point(point_id)
            elif refresh:
                self.update_point(point_id)
            self.revision += 1

    def remove_point(self, point_id: int) -> None:
        """Remove a point and every observation of it."""
        with self.lock:
            point = self.points.pop(point_id, None)
            if point is None:
                return
            self.table.drop(point_id)
            for keyframe_id, index in point.observations.items():
                self.keyframes[keyframe_id].point_ids[index] = -1
            if self.changes is not None:
                self.changes.gone(point_id)
                self.changes.keyframes.update(point.observations)
            self.revision += 1

    def merge_points(self, kept_id: int, merged_id: int, refresh: bool = True) -> None:
        """Fuse duplicate ``merged_id`` into ``kept_id``: its observations (in keyframes not already
        observing ``kept_id``) and counters move over, then it is removed (``refresh`` as in
        ``add_observation``)."""
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
            self.replaced[merged_id] = kept_id
            if self.changes is not None:
                self.changes.point(kept_id)
                self.changes.replaced[merged_id] = kept_id
            if refresh:
                self.update_point(kept_id)

    def update_point(self, point_id: int) -> None:
        """Recompute a point's representative descriptor, viewing direction and distance range (the
        lock held throughout: for a single point; ``refresh_points`` for many)."""
        with self.lock:
            point = self.points[point_id]
            self._set_summary(point, summarise([self._draft(point)], self.scale_factor, self.levels), 0)

    def refresh_points(self, point_ids: np.ndarray) -> None:
        """``update_point`` of every point of ``point_ids`` (P,) that exists: their observations read
        under the lock, the summaries computed without it, then written back under it to the points
        whose position and observations did not change meanwhile (whoever changed them updated them)."""
        with self.lock:
            points = [p for p in map(self.points.get, point_ids.tolist()) if p is not None]
            drafts = [self._draft(p) for p in points]
            seen = [(p.position, dict(p.observations)) for p in points]
        if not points:
            return
        summaries = summarise(drafts, self.scale_factor, self.levels)
        with self.lock:
            for n, (point, (position, observations)) in enumerate(zip(points, seen, strict=True)):
                if (self.points.get(point.id) is point and point.position is position
                        and point.observations == observations):
                    self._set_summary(point, summaries, n)

    def _draft(self, point: MapPoint) -> PointDraft:
        """What ``summarise`` needs of ``point`` (call with the database locked)."""
        observations = [(self.keyframes[k], i) for k, i in point.observations.items()]
        first = self.keyframes.get(point.first_keyframe, observations[0][0])
        return PointDraft(point.position, observations,
                          (first, point.observations.get(first.id, observations[0][1])))

    def _set_summary(self, point: MapPoint, summaries: PointSummaries, row: int) -> None:
        if self.changes is not None:
            self.changes.point(point.id)
        point.descriptor = summaries.descriptors[row]
        point.normal = summaries.normals[row]
        point.min_distance = float(summaries.min_distances[row])
        point.max_distance = float(summaries.max_distances[row])
        self.table.write(point)

    def set_pose(self, keyframe_id: int, T_camera_world: np.ndarray) -> None:
        """Keyframe ``keyframe_id`` gets the pose ``T_camera_world`` (4, 4)."""
        with self.lock:
            self.keyframes[keyframe_id].set_pose(T_camera_world)
            if self.changes is not None:
                self.changes.keyframes.add(keyframe_id)
            self.revision += 1

    def set_position(self, point_id: int, position: np.ndarray) -> None:
        """Point ``point_id``, if it exists, moves to ``position`` (3,) world."""
        with self.lock:
            if point_id in self.points:
                self.points[point_id].position = np.array(position, np.float64)
                self.table.write(self.points[point_id])
                if self.changes is not None:
                    self.changes.point(point_id)
                self.revision += 1

    def count_visible(self, point_ids: np.ndarray, found: np.ndarray | None = None) -> None:
        """Add one to ``visible`` of each point of ``point_ids`` (P,), and to ``found`` where ``found`` (P,) bool."""
        ids = point_ids.tolist()
        matched = [False] * len(ids) if found is None else np.asarray(found, bool).tolist()
        with self.lock:
            journal = self.counts
            for point_id, hit in zip(ids, matched, strict=True):
                point = self.points.get(point_id)
                if point is not None:
                    point.visible += 1
                    point.found += hit
                    if journal is not None:
                        journal.add(point_id, hit)

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

    def positions(self, point_ids: np.ndarray) -> np.ndarray:
        """(P, 3) world positions of the points ``point_ids`` that still exist (copies)."""
        with self.lock:
            return self.table.positions[self.table.existing(point_ids)]

    def arrays(self, point_ids: np.ndarray) -> PointArrays:
        """Copies of the data of the points ``point_ids`` that still exist, in their order."""
        with self.lock:
            return self.table.arrays(point_ids)
