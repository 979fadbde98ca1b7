"""Pose estimates: one target's pose, rigid bodies of a rig, ground truth.

A ``Pose`` is ``T_parent_child`` where the parent is ``header.frame_id`` (a camera's
optical frame for marker poses, ``world`` for rigid bodies, the map frame for SLAM) and the
child is ``child_frame_id`` (``marker/7``, ``body/wand``, the camera for SLAM). Its header is the
header of the frame it was estimated from.
"""

from __future__ import annotations

import math
from enum import StrEnum

from pydantic import Field, field_validator

from protocol.message import Message, Struct
from protocol.spatial import FrameTransform, Transform


class TrackingState(StrEnum):
    """Where a tracker stands for one target."""

    TRACKING = "tracking"
    """A fresh estimate from this frame's measurements."""
    RECOGNISED = "recognised"
    """A fresh estimate from this frame's measurements, found from scratch (a natural-feature target
    recognised by its descriptors) rather than followed on from the previous frame."""
    PREDICTED = "predicted"
    """No measurement in this frame; the pose is carried over or predicted."""
    INITIALIZING = "initializing"
    LOST = "lost"
    """No pose; ``Pose.reason`` may say why."""
    NO_CALIBRATION = "no_calibration"
    """The camera has no calibration, so no metric pose can be given."""


class PoseQuality(Struct):
    """Figures that say how far to trust a pose.

    ``reprojection_rms_px``: RMS of the measurement residuals in pixels; ``inliers``: the
    number of points (corners, spheres, features) that support the pose; ``ambiguous``:
    another pose explains the measurements almost as well (planar-target flip);
    ``residual_rms_m``: RMS distance (m) between measured 3D points and the fitted target's
    (a rigid body's spheres), None when the pose does not come from 3D points.
    """

    reprojection_rms_px: float | None = Field(default=None, ge=0)
    residual_rms_m: float | None = Field(default=None, ge=0)
    inliers: int = Field(default=0, ge=0)
    ambiguous: bool = False


Covariance6 = tuple[float, ...]


class Pose(Message):
    """One target's pose ``T_<header.frame_id>_<child_frame_id>`` with its quality.

    ``covariance`` is an optional row-major 6x6 matrix (36 numbers) over the perturbation
    (tx, ty, tz, rx, ry, rz) in the child frame: metres and radians. ``reason``: why a ``lost``
    pose has none, when the tracker knows (a natural-feature target: ``too_few_matches``, ...),
    else empty.

    Version 3 added the ``recognised`` state and ``reason``; versions 1 and 2 still decode.
    """

    SCHEMA = "artrack.Pose"
    VERSION = 3
    READS_OLDER = (1, 2)

    child_frame_id: str
    transform: Transform = Transform()
    state: TrackingState = TrackingState.TRACKING
    reason: str = ""
    quality: PoseQuality = PoseQuality()
    covariance: Covariance6 | None = None

    @field_validator("covariance")
    @classmethod
    def _six_by_six(cls, value: Covariance6 | None) -> Covariance6 | None:
        if value is not None and (len(value) != 36 or not all(math.isfinite(v) for v in value)):
            raise ValueError("covariance must hold 36 finite numbers (row-major 6x6)")
        return value


class RigidBody(Struct):
    """One rigid body of a rig: ``T_world_body`` with its state and quality."""

    name: str
    transform: Transform = Transform()
    state: TrackingState = TrackingState.TRACKING
    quality: PoseQuality = PoseQuality()


class RigidBodies(Message):
    """Every configured rigid body of a rig at one instant; ``header.frame_id`` is the world frame."""

    SCHEMA = "artrack.RigidBodies"
    VERSION = 2
    READS_OLDER = (1,)

    bodies: tuple[RigidBody, ...] = ()


class GroundTruth(Message):
    """Exact transforms known for one frame (synthetic scenes, motion capture).

    Each entry is ``T_parent_child``; which transforms a source publishes depends on the
    scene (``T_camera_marker`` per visible marker, ``T_world_body``, ``T_world_camera``).
    """

    SCHEMA = "artrack.GroundTruth"
    VERSION = 1

    transforms: tuple[FrameTransform, ...] = ()
