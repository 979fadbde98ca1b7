"""The covisibility graph of a map database: which keyframes observe common points, and how many.

Two keyframes are covisible when they observe common points; the edge's weight is how many. The
graph is read from the database's observations when asked and remembered until the database's next
change (its ``revision``), under the database's lock. A frame's local map (``local_keyframes``) is
the keyframes observing its matched points and their best covisible neighbours.
"""

from __future__ import annotations

import itertools
from collections import Counter

import numpy as np

from services.slam.map.database import MapDatabase

__all__ = ["NEIGHBOURS_OF", "CovisibilityGraph"]

NEIGHBOURS_OF = 5
"""A local map adds the covisible neighbours of this many of its keyframes (those sharing most points)."""


class CovisibilityGraph:
    """The covisibility of ``database``'s keyframes."""

    def __init__(self, database: MapDatabase):
        self.database = database
        self._weights: dict[int, Counter[int]] = {}
        self._revision = -1

    def covisibility(self, keyframe_id: int) -> Counter[int]:
        """Other keyframe id -> how many of ``keyframe_id``'s points it observes too (remembered until
        the database's next change)."""
        with self.database.lock:
            if self._revision != self.database.revision:
                self._weights.clear()
                self._revision = self.database.revision
            if keyframe_id not in self._weights:
                self._weights[keyframe_id] = self._count_covisible(keyframe_id)
            return Counter(self._weights[keyframe_id])

    def _count_covisible(self, keyframe_id: int) -> Counter[int]:
        database = self.database
        with database.lock:
            point_ids = database.keyframes[keyframe_id].point_ids
            points = database.points
            counts = Counter(itertools.chain.from_iterable(points[p].observations for p in
                                                           point_ids[point_ids >= 0].tolist()))
            counts.pop(keyframe_id, None)
            return counts

    def covisible(self, keyframe_id: int, count: int, least: int = 1) -> list[int]:
        """Up to ``count`` keyframes sharing at least ``least`` points with ``keyframe_id``, most shared first."""
        return [k for k, n in self.covisibility(keyframe_id).most_common(count) if n >= least]

    def observers(self, point_ids: np.ndarray) -> Counter[int]:
        """Keyframe id -> how many of the points ``point_ids`` (P,) it observes."""
        with self.database.lock:
            found = map(self.database.points.get, point_ids.tolist())
            return Counter(itertools.chain.from_iterable(p.observations for p in found if p is not None))

    def local_keyframes(self, point_ids: np.ndarray, count: int) -> list[int]:
        """The keyframes of a frame's local map: those observing its matched ``point_ids`` (P,), most
        shared first, then the best covisible neighbours of those; at most ``count``."""
        with self.database.lock:
            direct = [k for k, _ in self.observers(point_ids).most_common(count)]
            chosen = list(direct)
            for keyframe_id in direct[:NEIGHBOURS_OF]:
                if len(chosen) >= count:
                    break
                chosen.extend(k for k in self.covisible(keyframe_id, 10) if k not in chosen)
            return chosen[:count]
