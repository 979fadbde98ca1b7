"""Pose estimates: one target's pose, rigid bodies of a rig, ground truth.

A ``Pose`` is ``T_parent_child`` where the parent is ``header.frame_id`` (a camera's
optical frame for marker poses, ``world`` for rigid bodies, the map frame for SLAM) and the
child is ``child_frame_id`` (``marker/7``, ``body/wand``, the camera for SLAM). Its header is the
header of the frame it was estimated from. Its state is a ``TrackingState`` (``protocol.tracking_state``).
"""

from __future__ import annotations

import math
from typing import Annotated, Any

from pydantic import BeforeValidator, Field, field_validator

from protocol.message import Message, Struct
from protocol.spatial import FrameTransform, Transform
from protocol.tracking_state import TrackingState

OLD_SPELLINGS = {"initializing": TrackingState.INITIALISING}
"""States as older versions of ``Pose`` (1 to 3) and ``RigidBodies`` (1, 2) wrote them -> the state."""


def _state(value: Any) -> Any:
    return OLD_SPELLINGS.get(value, value) if isinstance(value, str) else value


WireState = Annotated[TrackingState, BeforeValidator(_state)]
"""A ``TrackingState`` as it travels; older versions' spellings (``OLD_SPELLINGS``) decode to theirs."""


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
    pose has none, when the tracker knows (a natural-feature target: ``too_few_matches``, ...);
    on a pose that has one, a warning that qualifies it (SLAM: ``calibration_suspect``); else empty.

    Version 3 added the ``recognised`` state and ``reason``, version 4 spells ``initialising`` so (versions
    1 to 3: ``initializing``); versions 1 to 3 still decode.
    """

    SCHEMA = "artrack.Pose"
    VERSION = 4
    READS_OLDER = (1, 2, 3)

    child_frame_id: str
    transform: Transform = Transform()
    state: WireState = TrackingState.TRACKING
    reason: str = ""
    quality: PoseQuality = PoseQuality()
    covariance: Covariance6 | None = None

    @field_validator("covariance")
    @classmethod
    def _six_by_six(cls, value: Covariance6 | None) -> Covariance6 | None:
        if value is not None and (len(value) != 36 or not all(map(math.isfinite, value))):
            raise ValueError("covariance must hold 36 finite numbers (row-major 6x6)")
        return value


class RigidBody(Struct):
    """One rigid body of a rig: ``T_world_body`` with its state and quality."""

    name: str
    transform: Transform = Transform()
    state: WireState = TrackingState.TRACKING
    quality: PoseQuality = PoseQuality()


class RigidBodies(Message):
    """Every configured rigid body of a rig at one instant; ``header.frame_id`` is the world frame.

    Version 3 spells the state ``initialising`` so (versions 1 and 2: ``initializing``); they still decode.
    """

    SCHEMA = "artrack.RigidBodies"
    VERSION = 3
    READS_OLDER = (1, 2)

    bodies: tuple[RigidBody, ...] = ()


class GroundTruth(Message):
    """Exact transforms known for one frame (synthetic scenes, motion capture).

    Each entry is ``T_parent_child``; which transforms a source publishes depends on the
    scene (``T_camera_marker`` per visible marker, ``T_world_body``, ``T_world_camera``).
    """

    SCHEMA = "artrack.GroundTruth"
    VERSION = 1

    transforms: tuple[FrameTransform, ...] = ()
