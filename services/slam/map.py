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
an ``RLock``; readers get copies, never live arrays. ``revision`` grows on every change. The
lock is held only while the map's dictionaries are read or changed: a point's summary (descriptor,
viewing direction, distance range) is computed from a snapshot of its observations outside the lock
and written back under it unless the point changed meanwhile (``refresh_points``, ``add_points``).

A map can also be kept in step with a copy in another process (``mapping_process``): ``record_changes``
makes it note which keyframes and points change, ``take_changes`` hands them over as ``MapChanges``
(copies) and ``apply_changes`` brings them into the copy; ``record_counts`` notes the tracking
counters added to the copy, for the other side's ``add_counts``; ``snapshot`` and ``restore`` copy a
whole map.
"""

from __future__ import annotations

import threading
from collections import Counter
from dataclasses import dataclass, field

import numpy as np

from services.slam.features import FrameFeatures

__all__ = ["Keyframe", "MapPoint", "SlamMap", "PointArrays", "MapChanges", "MapSnapshot"]

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
class MapChanges:
    """What changed in a map since the last ``SlamMap.take_changes``, as copies: ``keyframes`` id ->
    ``(T_camera_world (4, 4), point_ids (N,))`` of the keyframes whose pose or points changed (new ones
    included), ``points`` every added or changed point, ``removed`` the ids of removed points,
    ``replaced`` merged point id -> the id of the point it was merged into."""

    keyframes: dict[int, tuple[np.ndarray, np.ndarray]]
    points: list[MapPoint]
    removed: list[int]
    replaced: dict[int, int]


@dataclass(frozen=True)
class MapSnapshot:
    """A whole map as copies: its ``keyframes`` and ``points``, and the ids the next ones get."""

    keyframes: list[Keyframe]
    points: list[MapPoint]
    next_keyframe: int
    next_point: int


@dataclass
class _Changed:
    """The ids noted for the next ``MapChanges``."""

    keyframes: set[int] = field(default_factory=set)
    points: set[int] = field(default_factory=set)
    removed: set[int] = field(default_factory=set)
    replaced: dict[int, int] = field(default_factory=dict)

    def point(self, point_id: int) -> None:
        self.points.add(point_id)
        self.removed.discard(point_id)

    def gone(self, point_id: int) -> None:
        self.points.discard(point_id)
        self.removed.add(point_id)


def _copy_point(point: MapPoint) -> MapPoint:
    return MapPoint(point.id, point.position.copy(), dict(point.observations), point.first_keyframe,
                    point.descriptor.copy(), point.normal.copy(), point.min_distance, point.max_distance,
                    point.visible, point.found)


def _copy_keyframe(keyframe: Keyframe) -> Keyframe:
    return Keyframe(keyframe.id, keyframe.stamp_ns, keyframe.T_camera_world.copy(), keyframe.features,
                    keyframe.point_ids.copy())


@dataclass(frozen=True)
class _Draft:
    """A point's summary to compute: ``position`` (3,) world, ``observations`` (keyframe, keypoint
    index) in observation order, ``first`` (keyframe, keypoint index) that sets the distance range."""

    position: np.ndarray
    observations: list[tuple[Keyframe, int]]
    first: tuple[Keyframe, int]


@dataclass(frozen=True)
class _Summaries:
    """P points' ``descriptors`` (P, 32) uint8, ``normals`` (P, 3), ``min_distances``, ``max_distances`` (P,)."""

    descriptors: np.ndarray
    normals: np.ndarray
    min_distances: np.ndarray
    max_distances: np.ndarray


def _median_descriptors(descriptors: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """(P, 32): each point's descriptor with the least median Hamming distance to its others (the
    first when it has one or two); ``descriptors`` (O, 32) the points' observations one after the
    other, ``counts`` (P,) how many each."""
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
    chosen = starts.copy()
    for count in np.unique(counts[counts > 2]).tolist():
        rows = np.flatnonzero(counts == count)
        group = descriptors[starts[rows, None] + np.arange(count)]
        distances = np.bitwise_count(group[:, :, None, :] ^ group[:, None, :, :]).sum(axis=3, dtype=np.int32)
        medians = np.sort(distances, axis=2)[:, :, (count - 1) // 2]
        chosen[rows] = starts[rows] + np.argmin(medians, axis=1)
    return descriptors[chosen].copy()


def _gather(keyframes: list[Keyframe], indices: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(descriptors (O, 32), levels (O,), centres (O, 3))`` of keypoint ``indices[o]`` of ``keyframes[o]``."""
    ids = np.array([k.id for k in keyframes], np.int64)
    descriptors, levels = np.zeros((len(ids), 32), np.uint8), np.zeros(len(ids), np.int64)
    centres = np.zeros((len(ids), 3))
    for keyframe in {k.id: k for k in keyframes}.values():
        rows = np.flatnonzero(ids == keyframe.id)
        descriptors[rows] = keyframe.features.descriptors[indices[rows]]
        levels[rows] = keyframe.features.levels[indices[rows]]
        centres[rows] = keyframe.centre
    return descriptors, levels, centres


def _summarise(drafts: list[_Draft], scale_factor: float, levels: int) -> _Summaries:
    """The summaries of ``drafts`` (needs no lock: keyframes' features never change, and a pose
    change replaces a keyframe's ``centre`` rather than writing into it)."""
    counts = np.array([len(d.observations) for d in drafts], np.int64)
    observed = [k for d in drafts for k, _ in d.observations]
    descriptors, _, centres = _gather(observed, np.array([i for d in drafts for _, i in d.observations], np.int64))
    positions = np.array([d.position for d in drafts], np.float64).reshape(-1, 3)
    rays = np.repeat(positions, counts, axis=0) - centres
    rays /= np.maximum(np.linalg.norm(rays, axis=1), 1e-12)[:, None]
    owner = np.repeat(np.arange(len(drafts)), counts)
    mean = np.stack([np.bincount(owner, rays[:, c], len(drafts)) for c in range(3)], axis=1)
    normals = mean / np.maximum(np.linalg.norm(mean, axis=1), 1e-12)[:, None]
    _, first_levels, first_centres = _gather([d.first[0] for d in drafts],
                                             np.array([d.first[1] for d in drafts], np.int64))
    max_distances = np.linalg.norm(positions - first_centres, axis=1) * scale_factor ** first_levels
    return _Summaries(_median_descriptors(descriptors, counts), normals,
                      max_distances / scale_factor ** (levels - 1), max_distances)


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
        self._changed: _Changed | None = None
        self._counts: dict[int, list[int]] | None = None
        self.replaced: dict[int, int] = {}
        """Merged point id -> the id of the point it was merged into (``resolve``)."""

    def record_changes(self) -> None:
        """From now on, note every keyframe and point that changes (for ``take_changes``)."""
        with self.lock:
            self._changed = _Changed()

    def record_counts(self) -> None:
        """From now on, note the counters ``count_visible`` adds (for ``take_counts``)."""
        with self.lock:
            self._counts = {}

    def take_changes(self) -> MapChanges:
        """Copies of what changed since the last call (``record_changes`` first), and a fresh start."""
        with self.lock:
            changed, self._changed = self._changed or _Changed(), _Changed()
            keyframes = {k: (self.keyframes[k].T_camera_world.copy(), self.keyframes[k].point_ids.copy())
                         for k in sorted(changed.keyframes) if k in self.keyframes}
            points = [_copy_point(self.points[p]) for p in sorted(changed.points) if p in self.points]
            return MapChanges(keyframes, points, sorted(changed.removed), dict(changed.replaced))

    def take_counts(self) -> dict[int, tuple[int, int]]:
        """Point id -> ``(visible, found)`` added by ``count_visible`` since the last call (``record_counts`` first)."""
        with self.lock:
            counts, self._counts = self._counts or {}, {}
            return {p: (v, f) for p, (v, f) in counts.items()}

    def add_counts(self, counts: dict[int, tuple[int, int]]) -> None:
        """Add counters taken from a copy of this map (``take_counts``) to the points that still exist."""
        with self.lock:
            for point_id, (visible, found) in counts.items():
                point = self.points.get(point_id)
                if point is not None:
                    point.visible += visible
                    point.found += found

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

    def snapshot(self) -> MapSnapshot:
        """Copies of every keyframe and point (keypoint features are shared: they never change)."""
        with self.lock:
            return MapSnapshot([_copy_keyframe(k) for k in self.keyframes.values()],
                               [_copy_point(p) for p in self.points.values()], self._next_keyframe, self._next_point)

    def restore(self, snapshot: MapSnapshot) -> None:
        """Become the map of ``snapshot`` (copied); changes noted so far are dropped."""
        with self.lock:
            self.keyframes = {k.id: _copy_keyframe(k) for k in snapshot.keyframes}
            self.points = {p.id: _copy_point(p) for p in snapshot.points}
            self._next_keyframe, self._next_point = snapshot.next_keyframe, snapshot.next_point
            self.replaced = {}
            if self._changed is not None:
                self._changed = _Changed()
            self.revision += 1

    def apply_changes(self, changes: MapChanges, pending: list[int]) -> None:
        """Bring in ``changes`` made to a copy of this map that knows every keyframe of this one but those
        of ``pending``: their keyframes and points replace these (``changes`` is taken over, not copied),
        removed points go; then the observations of the ``pending`` keyframes are linked again (to points
        that still exist) in the points that came without them."""
        with self.lock:
            for point_id in changes.removed:
                self.points.pop(point_id, None)
            for keyframe_id, (T, point_ids) in changes.keyframes.items():
                keyframe = self.keyframes.get(keyframe_id)
                if keyframe is not None:
                    keyframe.set_pose(T)
                    keyframe.point_ids = point_ids
            for point in changes.points:
                self.points[point.id] = point
                self._next_point = max(self._next_point, point.id + 1)
            self.replaced.update(changes.replaced)
            touched_ids = np.array([p.id for p in changes.points] + list(changes.removed), np.int64)
            for pending_id in pending:
                newer = self.keyframes.get(pending_id)
                if newer is None:
                    continue
                indices = np.flatnonzero(np.isin(newer.point_ids, touched_ids))
                for index, point_id in zip(indices.tolist(), self.resolve(newer.point_ids[indices]).tolist(),
                                           strict=True):
                    seen = self.points.get(point_id)
                    if seen is None or seen.observations.get(pending_id, index) != index:
                        newer.point_ids[index] = -1
                    else:
                        newer.point_ids[index] = point_id
                        seen.observations[pending_id] = index
            self.revision += 1

    def clear(self) -> None:
        """Forget every keyframe and point."""
        with self.lock:
            self.keyframes.clear()
            self.points.clear()
            self.replaced.clear()
            if self._changed is not None:
                self._changed = _Changed()
            self.revision += 1

    def add_keyframe(self, stamp_ns: int, T_camera_world: np.ndarray, features: FrameFeatures,
                     point_ids: np.ndarray, keyframe_id: int | None = None) -> Keyframe:
        """A new keyframe (its id ``keyframe_id``, as a copy of this map named it, or the next); each
        keypoint ``i`` with ``point_ids[i] >= 0`` (an existing point, or one merged into it since:
        ``resolve``) becomes an observation of that point (ids of points since removed are dropped)."""
        with self.lock:
            new_id = self._next_keyframe if keyframe_id is None else keyframe_id
            keyframe = Keyframe(new_id, stamp_ns, np.array(T_camera_world, np.float64), features,
                                np.full(len(features), -1, np.int64))
            self._next_keyframe = max(self._next_keyframe, new_id + 1)
            self.keyframes[keyframe.id] = keyframe
            if self._changed is not None:
                self._changed.keyframes.add(keyframe.id)
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
            point = MapPoint(self._next_point, np.array(position, np.float64), {}, min(observations))
            self._next_point += 1
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
        drafts = [_Draft(positions[row], [(found[k], i) for k, i in observations[row].items()],
                         (found[min(found)], observations[row][min(found)])) for row, found in candidates]
        summaries = _summarise(drafts, self.scale_factor, self.levels) if drafts else None
        made: list[int] = []
        with self.lock:
            for n, (row, found) in enumerate(candidates):
                if any(self.keyframes.get(k) is not found[k] or found[k].point_ids[i] >= 0
                       for k, i in observations[row].items()):
                    continue
                point = MapPoint(self._next_point, np.array(positions[row], np.float64), {}, min(found))
                self._next_point += 1
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
        if self._changed is not None:
            self._changed.point(point.id)
            self._changed.keyframes.add(keyframe.id)

    def remove_observation(self, point_id: int, keyframe_id: int, refresh: bool = True) -> None:
        """Drop one observation; a point left with fewer than two is removed (``refresh`` as in
        ``add_observation``)."""
        with self.lock:
            point = self.points.get(point_id)
            if point is None or keyframe_id not in point.observations:
                return
            index = point.observations.pop(keyframe_id)
            self.keyframes[keyframe_id].point_ids[index] = -1
            if self._changed is not None:
                self._changed.point(point_id)
                self._changed.keyframes.add(keyframe_id)
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
            for keyframe_id, index in point.observations.items():
                self.keyframes[keyframe_id].point_ids[index] = -1
            if self._changed is not None:
                self._changed.gone(point_id)
                self._changed.keyframes.update(point.observations)
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
            if self._changed is not None:
                self._changed.point(kept_id)
                self._changed.replaced[merged_id] = kept_id
            if refresh:
                self.update_point(kept_id)

    def update_point(self, point_id: int) -> None:
        """Recompute a point's representative descriptor, viewing direction and distance range (the
        lock held throughout: for a single point; ``refresh_points`` for many)."""
        with self.lock:
            point = self.points[point_id]
            self._set_summary(point, _summarise([self._draft(point)], self.scale_factor, self.levels), 0)

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
        summaries = _summarise(drafts, self.scale_factor, self.levels)
        with self.lock:
            for n, (point, (position, observations)) in enumerate(zip(points, seen, strict=True)):
                if (self.points.get(point.id) is point and point.position is position
                        and point.observations == observations):
                    self._set_summary(point, summaries, n)

    def _draft(self, point: MapPoint) -> _Draft:
        """What ``_summarise`` needs of ``point`` (call with the map locked)."""
        observations = [(self.keyframes[k], i) for k, i in point.observations.items()]
        first = self.keyframes.get(point.first_keyframe, observations[0][0])
        return _Draft(point.position, observations,
                      (first, point.observations.get(first.id, observations[0][1])))

    def _set_summary(self, point: MapPoint, summaries: _Summaries, row: int) -> None:
        if self._changed is not None:
            self._changed.point(point.id)
        point.descriptor = summaries.descriptors[row]
        point.normal = summaries.normals[row]
        point.min_distance = float(summaries.min_distances[row])
        point.max_distance = float(summaries.max_distances[row])

    def set_pose(self, keyframe_id: int, T_camera_world: np.ndarray) -> None:
        with self.lock:
            self.keyframes[keyframe_id].set_pose(T_camera_world)
            if self._changed is not None:
                self._changed.keyframes.add(keyframe_id)
            self.revision += 1

    def set_position(self, point_id: int, position: np.ndarray) -> None:
        with self.lock:
            if point_id in self.points:
                self.points[point_id].position = np.array(position, np.float64)
                if self._changed is not None:
                    self._changed.point(point_id)
                self.revision += 1

    def count_visible(self, point_ids: np.ndarray, found: np.ndarray | None = None) -> None:
        """Add one to ``visible`` of each point of ``point_ids`` (P,), and to ``found`` where ``found`` (P,) bool."""
        with self.lock:
            for k, point_id in enumerate(point_ids.tolist()):
                point = self.points.get(point_id)
                if point is not None:
                    point.visible += 1
                    point.found += int(found is not None and found[k])
                    if self._counts is not None:
                        counted = self._counts.setdefault(point_id, [0, 0])
                        counted[0] += 1
                        counted[1] += int(found is not None and found[k])

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

    def positions(self, point_ids: np.ndarray) -> np.ndarray:
        """(P, 3) world positions of the points ``point_ids`` that still exist (copies)."""
        with self.lock:
            positions = [self.points[i].position for i in point_ids.tolist() if i in self.points]
        return np.array(positions, np.float64).reshape(-1, 3)

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
        Returns how many were removed. The points are judged outside the lock (their counters read as
        they are then) and judged again under it when removed."""

        def failed(p: MapPoint) -> bool:
            return newest_keyframe - p.first_keyframe <= probation and (
                p.found < min_found_ratio * p.visible
                or (newest_keyframe - p.first_keyframe >= 2 and len(p.observations) < min_observations))

        with self.lock:
            points = list(self.points.values())
        doomed = [p for p in points if failed(p)]
        with self.lock:
            removed = [p.id for p in doomed if self.points.get(p.id) is p and failed(p)]
            for point_id in removed:
                self.remove_point(point_id)
            return len(removed)
