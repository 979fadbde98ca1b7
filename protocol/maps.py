"""Maps: 3D points (triangulated markers, SLAM map points), the keyframes of a SLAM map and the final
trajectory of a SLAM run."""

from __future__ import annotations

from typing import Annotated

import numpy as np
from pydantic import model_validator

from protocol.arrays import array_field
from protocol.message import Message


def _check_rigid(poses: np.ndarray, what: str) -> None:
    """ValueError unless every (N, 4, 4) pose has the last row 0 0 0 1."""
    if len(poses) and not np.array_equal(poses[:, 3], np.broadcast_to([0.0, 0.0, 0.0, 1.0], (len(poses), 4))):
        raise ValueError(f"{what} poses must be rigid transforms: last row 0 0 0 1")


class PointCloud(Message):
    """3D points in ``header.frame_id``.

    ``points``: (N, 3) float32 metres; ``ids``: (N,) int64 stable point ids (map point
    ids for SLAM); ``colors``: (N, 3) uint8 BGR, or (0, 3) when the points have no colour.
    """

    SCHEMA = "artrack.PointCloud"
    VERSION = 1

    points: Annotated[np.ndarray, array_field("float32", (None, 3))]
    ids: Annotated[np.ndarray, array_field("int64", (None,))]
    colors: Annotated[np.ndarray, array_field("uint8", (None, 3))]

    @model_validator(mode="after")
    def _aligned(self) -> PointCloud:
        if len(self.ids) != len(self.points) or len(self.colors) not in (0, len(self.points)):
            raise ValueError(
                f"{len(self.points)} points need as many ids (got {len(self.ids)}) "
                f"and as many colours or none (got {len(self.colors)})"
            )
        return self


class Keyframes(Message):
    """The keyframes of a SLAM map: ``T_<header.frame_id>_<child_frame_id>`` of each, the map frame to the camera.

    ``ids``: (K,) int64 keyframe ids; ``stamps_ns``: (K,) int64 capture stamps of the frames they were made
    from; ``poses``: (K, 4, 4) float64 rigid transforms (last row 0 0 0 1), metres of the map's scale. Rows are
    aligned. The header is that of the frame after which the keyframes last changed (one was added, or the
    map's optimisation moved them); every message holds the whole set.
    """

    SCHEMA = "artrack.Keyframes"
    VERSION = 1

    child_frame_id: str
    ids: Annotated[np.ndarray, array_field("int64", (None,))]
    stamps_ns: Annotated[np.ndarray, array_field("int64", (None,))]
    poses: Annotated[np.ndarray, array_field("float64", (None, 4, 4))]

    @model_validator(mode="after")
    def _aligned(self) -> Keyframes:
        if not len(self.ids) == len(self.stamps_ns) == len(self.poses):
            raise ValueError(f"{len(self.ids)} keyframe ids need as many stamps (got {len(self.stamps_ns)}) and "
                             f"poses (got {len(self.poses)})")
        _check_rigid(self.poses, "keyframe")
        return self


class Trajectory(Message):
    """The final trajectory of a SLAM map: ``T_<header.frame_id>_<child_frame_id>`` of every frame tracked, each
    through its reference keyframe's bundle-adjusted pose, as SLAM benchmarks score a run.

    ``stamps_ns``: (N,) int64 the frames' stamps; ``seqs``: (N,) int64 their sequence numbers; ``poses``: (N, 4, 4)
    float64 rigid transforms (last row 0 0 0 1), in the map's scale. Rows are aligned, oldest frame first. The
    header is that of the last frame the map took; every message holds the whole trajectory.
    """

    SCHEMA = "artrack.Trajectory"
    VERSION = 1

    child_frame_id: str
    stamps_ns: Annotated[np.ndarray, array_field("int64", (None,))]
    seqs: Annotated[np.ndarray, array_field("int64", (None,))]
    poses: Annotated[np.ndarray, array_field("float64", (None, 4, 4))]

    @model_validator(mode="after")
    def _aligned(self) -> Trajectory:
        if not len(self.stamps_ns) == len(self.seqs) == len(self.poses):
            raise ValueError(f"{len(self.poses)} poses need as many stamps (got {len(self.stamps_ns)}) and sequence "
                             f"numbers (got {len(self.seqs)})")
        _check_rigid(self.poses, "trajectory")
        return self
