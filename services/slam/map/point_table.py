"""The map points' data that tracking reads every frame, kept as arrays with one row per point id.

A frame's searches read a few thousand points' positions, descriptors, viewing directions and
distance ranges (``PointArrays``); gathering them from the ``MapPoint`` objects one by one costs a
Python step per point and field. The table keeps a copy of those fields in rows indexed by the point's
id, written whenever the database changes a point's position or summary, so that reading any set of
points is one indexing of each array. The ``MapPoint`` objects stay the map's own record.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from services.slam.map.map_point import MapPoint, PointArrays

__all__ = ["PointTable"]

FIRST_ROWS = 1024


class PointTable:
    """Rows indexed by point id: ``positions`` (C, 3) world, ``descriptors`` (C, 32) uint8, ``normals``
    (C, 3), ``min_distances`` and ``max_distances`` (C,), and ``present`` (C,) bool: whether the id is a
    point of the map now. Rows grow (doubling) to hold the largest id written."""

    def __init__(self) -> None:
        self._allocate(FIRST_ROWS)

    def _allocate(self, rows: int) -> None:
        self.positions = np.zeros((rows, 3))
        self.descriptors = np.zeros((rows, 32), np.uint8)
        self.normals = np.zeros((rows, 3))
        self.min_distances = np.zeros(rows)
        self.max_distances = np.full(rows, np.inf)
        self.present = np.zeros(rows, bool)

    def _columns(self) -> tuple[np.ndarray, ...]:
        return self.positions, self.descriptors, self.normals, self.min_distances, self.max_distances, self.present

    def _grow(self, rows: int) -> None:
        old = self._columns()
        self._allocate(rows)
        for new, kept in zip(self._columns(), old, strict=True):
            new[:len(kept)] = kept

    def write(self, point: MapPoint) -> None:
        """``point``'s fields into its row (now present)."""
        self._put(point.id, point.position, point.descriptor, point.normal, point.min_distance, point.max_distance)

    def write_arrays(self, arrays: PointArrays) -> None:
        """The rows of ``arrays``' points (now present)."""
        if len(arrays):
            self._put(arrays.ids, arrays.positions, arrays.descriptors, arrays.normals, arrays.min_distances,
                      arrays.max_distances)

    def _put(self, rows: int | np.ndarray, positions: np.ndarray, descriptors: np.ndarray, normals: np.ndarray,
             min_distances: float | np.ndarray, max_distances: float | np.ndarray) -> None:
        """The fields of the points of ``rows`` (one id, or (P,) ids), the table grown to hold them."""
        highest = int(np.max(rows))
        if highest >= len(self.present):
            self._grow(max(2 * len(self.present), highest + 1))
        self.positions[rows] = positions
        self.descriptors[rows] = descriptors
        self.normals[rows] = normals
        self.min_distances[rows] = min_distances
        self.max_distances[rows] = max_distances
        self.present[rows] = True

    def drop(self, point_id: int) -> None:
        """The point ``point_id`` is no longer in the map."""
        if 0 <= point_id < len(self.present):
            self.present[point_id] = False

    def rebuild(self, points: Iterable[MapPoint]) -> None:
        """Only ``points``, written afresh."""
        self.present[:] = False
        for point in points:
            self.write(point)

    def existing(self, point_ids: np.ndarray) -> np.ndarray:
        """The ids of ``point_ids`` (P,) that are points of the map, in their order (repeats kept)."""
        ids = np.asarray(point_ids, np.int64).reshape(-1)
        inside = (ids >= 0) & (ids < len(self.present))
        inside[inside] = self.present[ids[inside]]
        return ids[inside]

    def arrays(self, point_ids: np.ndarray) -> PointArrays:
        """Copies of the rows of the ``point_ids`` (P,) that are points of the map, in their order."""
        ids = self.existing(point_ids)
        return PointArrays(ids=ids, positions=self.positions[ids], descriptors=self.descriptors[ids],
                           normals=self.normals[ids], min_distances=self.min_distances[ids],
                           max_distances=self.max_distances[ids])
