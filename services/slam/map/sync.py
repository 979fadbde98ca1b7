"""A map database kept in step with a copy of it in another process (``mapping_process``).

The tracker's database sends the whole map once (``snapshot``; the copy ``restore``s it) and then the
tracking counters it added (``record_counts`` to start noting them, ``take_counts`` to hand them over,
``add_counts`` on the other side). The copy notes what its mapper changes (``record_changes``),
hands it over as ``MapChanges`` (``take_changes``), and the tracker's database brings them in
(``apply_changes``). Everything that crosses is a copy; keypoint features are shared, as they never
change. Changed points cross as columns (``map_point.PointColumns``): unpickling a few arrays costs the
tracker far less than a point object with three small arrays for each point.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.slam.map.database import MapDatabase
from services.slam.map.journal import ChangeJournal, CountJournal
from services.slam.map.keyframe import Keyframe
from services.slam.map.map_point import MapPoint, PointColumns

__all__ = ["MapChanges", "MapSnapshot", "add_counts", "apply_changes", "record_changes", "record_counts",
           "restore", "snapshot", "take_changes", "take_counts"]


@dataclass(frozen=True)
class MapChanges:
    """What changed in a map since the last ``take_changes``, as copies: ``keyframes`` id ->
    ``(T_camera_world (4, 4), point_ids (N,))`` of the keyframes whose pose or points changed (new ones
    included), ``points`` every added or changed point (as columns), ``removed`` the ids of removed points,
    ``replaced`` merged point id -> the id of the point it was merged into."""

    keyframes: dict[int, tuple[np.ndarray, np.ndarray]]
    points: PointColumns
    removed: list[int]
    replaced: dict[int, int]


@dataclass(frozen=True)
class MapSnapshot:
    """A whole map as copies: its ``keyframes`` and ``points``, and the ids the next ones get."""

    keyframes: list[Keyframe]
    points: list[MapPoint]
    next_keyframe_id: int
    next_point_id: int


def record_changes(database: MapDatabase) -> None:
    """From now on, ``database`` notes every keyframe and point that changes (for ``take_changes``)."""
    with database.lock:
        database.changes = ChangeJournal()


def take_changes(database: MapDatabase) -> MapChanges:
    """Copies of what changed in ``database`` since the last call (``record_changes`` first), and a fresh start."""
    with database.lock:
        changed, database.changes = database.changes or ChangeJournal(), ChangeJournal()
        keyframes = {k: (database.keyframes[k].T_camera_world.copy(), database.keyframes[k].point_ids.copy())
                     for k in sorted(changed.keyframes) if k in database.keyframes}
        points = PointColumns.of([database.points[p] for p in sorted(changed.points) if p in database.points])
        return MapChanges(keyframes, points, sorted(changed.removed), dict(changed.replaced))


def record_counts(database: MapDatabase) -> None:
    """From now on, ``database`` notes the counters ``count_visible`` adds (for ``take_counts``)."""
    with database.lock:
        database.counts = CountJournal()


def take_counts(database: MapDatabase) -> dict[int, tuple[int, int]]:
    """Point id -> ``(visible, found)`` added by ``count_visible`` since the last call (``record_counts`` first)."""
    with database.lock:
        counts, database.counts = database.counts or CountJournal(), CountJournal()
        return {p: (v, f) for p, (v, f) in counts.counts.items()}


def add_counts(database: MapDatabase, counts: dict[int, tuple[int, int]]) -> None:
    """Add counters taken from a copy of ``database`` (``take_counts``) to the points that still exist."""
    with database.lock:
        for point_id, (visible, found) in counts.items():
            point = database.points.get(point_id)
            if point is not None:
                point.visible += visible
                point.found += found


def snapshot(database: MapDatabase) -> MapSnapshot:
    """Copies of every keyframe and point of ``database``."""
    with database.lock:
        return MapSnapshot([k.copy() for k in database.keyframes.values()],
                           [p.copy() for p in database.points.values()],
                           database.next_keyframe_id, database.next_point_id)


def restore(database: MapDatabase, map_snapshot: MapSnapshot) -> None:
    """``database`` becomes the map of ``map_snapshot`` (copied); changes noted so far are dropped."""
    with database.lock:
        database.keyframes = {k.id: k.copy() for k in map_snapshot.keyframes}
        database.points = {p.id: p.copy() for p in map_snapshot.points}
        database.table.rebuild(database.points.values())
        database.next_keyframe_id, database.next_point_id = map_snapshot.next_keyframe_id, map_snapshot.next_point_id
        database.replaced = {}
        if database.changes is not None:
            database.changes = ChangeJournal()
        database.revision += 1


def apply_changes(database: MapDatabase, changes: MapChanges, pending: list[int]) -> None:
    """Bring into ``database`` the ``changes`` made to a copy of it that knows every keyframe of it but
    those of ``pending``: their keyframes and points replace these (``changes`` is taken over, not
    copied), removed points go; then the observations of the ``pending`` keyframes are linked again (to
    points that still exist) in the points that came without them."""
    with database.lock:
        for point_id in changes.removed:
            database.points.pop(point_id, None)
            database.table.drop(point_id)
        for keyframe_id, (T, point_ids) in changes.keyframes.items():
            keyframe = database.keyframes.get(keyframe_id)
            if keyframe is not None:
                keyframe.set_pose(T)
                keyframe.point_ids = point_ids
        changed = changes.points.arrays.ids
        database.points.update(zip(changed.tolist(), changes.points.points(), strict=True))
        database.table.write_arrays(changes.points.arrays)
        if len(changed):
            database.next_point_id = max(database.next_point_id, int(changed.max()) + 1)
        database.replaced.update(changes.replaced)
        touched_ids = np.r_[changed, np.array(changes.removed, np.int64)]
        for pending_id in pending:
            newer = database.keyframes.get(pending_id)
            if newer is None:
                continue
            indices = np.flatnonzero(np.isin(newer.point_ids, touched_ids))
            for index, point_id in zip(indices.tolist(), database.resolve(newer.point_ids[indices]).tolist(),
                                       strict=True):
                seen = database.points.get(point_id)
                if seen is None or seen.observations.get(pending_id, index) != index:
                    newer.point_ids[index] = -1
                else:
                    newer.point_ids[index] = point_id
                    seen.observations[pending_id] = index
        database.revision += 1
