"""A map point, and the data of many map points as arrays: what tracking reads (``PointArrays``), and
whole points as columns (``PointColumns``, what crosses between processes: a few arrays pickle and
unpickle far faster than as many small arrays per point)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["MapPoint", "PointArrays", "PointColumns"]


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

    def copy(self) -> MapPoint:
        """A copy that shares no array or dictionary with this point."""
        return MapPoint(self.id, self.position.copy(), dict(self.observations), self.first_keyframe,
                        self.descriptor.copy(), self.normal.copy(), self.min_distance, self.max_distance,
                        self.visible, self.found)


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


@dataclass(frozen=True)
class PointColumns:
    """P whole map points as columns: ``arrays`` their ids, positions and summaries; ``first_keyframes``,
    ``visible``, ``found`` (P,) int64; their observations in point order, point ``i``'s at
    ``observed_keyframes[offsets[i]:offsets[i + 1]]`` (keyframe ids) and ``observed_keypoints`` (keypoint
    indices), ``offsets`` (P + 1,) int64."""

    arrays: PointArrays
    first_keyframes: np.ndarray
    visible: np.ndarray
    found: np.ndarray
    offsets: np.ndarray
    observed_keyframes: np.ndarray
    observed_keypoints: np.ndarray

    def __len__(self) -> int:
        return len(self.arrays)

    @staticmethod
    def of(points: list[MapPoint]) -> PointColumns:
        """The columns of ``points`` (copies)."""
        arrays = PointArrays(ids=np.array([p.id for p in points], np.int64),
                             positions=np.array([p.position for p in points], np.float64).reshape(-1, 3),
                             descriptors=np.array([p.descriptor for p in points], np.uint8).reshape(-1, 32),
                             normals=np.array([p.normal for p in points], np.float64).reshape(-1, 3),
                             min_distances=np.array([p.min_distance for p in points], np.float64),
                             max_distances=np.array([p.max_distance for p in points], np.float64))
        counts = np.array([len(p.observations) for p in points], np.int64)
        return PointColumns(arrays, np.array([p.first_keyframe for p in points], np.int64),
                            np.array([p.visible for p in points], np.int64),
                            np.array([p.found for p in points], np.int64), np.r_[0, np.cumsum(counts)],
                            np.array([k for p in points for k in p.observations], np.int64),
                            np.array([i for p in points for i in p.observations.values()], np.int64))

    def points(self) -> list[MapPoint]:
        """The points again (their arrays are rows of these columns, shared, as points' arrays are replaced,
        never written in place)."""
        a = self.arrays
        offsets, keyframes, keypoints = self.offsets.tolist(), self.observed_keyframes.tolist(), \
            self.observed_keypoints.tolist()
        return [MapPoint(point_id, a.positions[row], dict(zip(keyframes[start:end], keypoints[start:end], strict=True)),
                         first, a.descriptors[row], a.normals[row], low, high, visible, found)
                for row, (point_id, start, end, first, low, high, visible, found) in enumerate(zip(
                    a.ids.tolist(), offsets[:-1], offsets[1:], self.first_keyframes.tolist(),
                    a.min_distances.tolist(), a.max_distances.tolist(), self.visible.tolist(), self.found.tolist(),
                    strict=True))]
