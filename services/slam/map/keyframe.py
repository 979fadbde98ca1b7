"""A keyframe of the map: a frame kept with its pose, its features and the map point each keypoint observes."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from services.slam.features import FrameFeatures

__all__ = ["Keyframe"]


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

    def copy(self) -> Keyframe:
        """A copy whose pose and point ids are its own (the features are shared: they never change)."""
        return Keyframe(self.id, self.stamp_ns, self.T_camera_world.copy(), self.features, self.point_ids.copy())
