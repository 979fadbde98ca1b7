"""What a map database notes of its changes while a copy of it is kept in another process (``sync``).

A ``ChangeJournal`` holds the ids of the keyframes and points that changed (the mapping process's
copy, for the tracker); a ``CountJournal`` the tracking counters added to points (the tracker's map,
for the mapping process). The database feeds whichever it has (``MapDatabase.changes``,
``MapDatabase.counts``); ``sync`` turns them into messages.
"""

from __future__ import annotations

from dataclasses import dataclass, field

__all__ = ["ChangeJournal", "CountJournal"]


@dataclass
class ChangeJournal:
    """The ids noted for the next ``sync.MapChanges``: ``keyframes`` whose pose or point ids changed (new
    ones included), ``points`` added or changed, ``removed`` points, ``replaced`` merged point id -> the
    id of the point it was merged into."""

    keyframes: set[int] = field(default_factory=set)
    points: set[int] = field(default_factory=set)
    removed: set[int] = field(default_factory=set)
    replaced: dict[int, int] = field(default_factory=dict)

    def point(self, point_id: int) -> None:
        """Point ``point_id`` was added or changed."""
        self.points.add(point_id)
        self.removed.discard(point_id)

    def gone(self, point_id: int) -> None:
        """Point ``point_id`` was removed."""
        self.points.discard(point_id)
        self.removed.add(point_id)


@dataclass
class CountJournal:
    """``counts``: point id -> ``[visible, found]`` added since the journal began."""

    counts: dict[int, list[int]] = field(default_factory=dict)

    def add(self, point_id: int, found: bool) -> None:
        """Point ``point_id`` fell in a tracked frame's view, and was matched there if ``found``."""
        counted = self.counts.setdefault(point_id, [0, 0])
        counted[0] += 1
        counted[1] += int(found)
