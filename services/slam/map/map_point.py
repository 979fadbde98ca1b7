"""A map point, and the data of many map points as arrays."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["MapPoint", "PointArrays"]


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
