"""Rigid transforms as they travel: translation in metres, rotation as a unit quaternion.

A ``Transform`` named ``T_a_b`` maps coordinates in frame b to frame a
(``p_a = R @ p_b + t``). The quaternion is ``(x, y, z, w)``; it is normalised on
validation and refused when its norm is far from 1 (a sign of a wrong field order or
garbage). Conversions to matrices live in ``services.geometry``; the protocol holds data only.

``StaticTransforms`` is a rig's ``tf_static``: transforms that do not change while the rig
runs (each camera's ``T_rig_camera``, with ``RIG_FRAME`` as parent and the camera's name,
its images' ``header.frame_id``, as child).
"""

from __future__ import annotations

import math
import sys

from pydantic import field_validator

from protocol.message import Message, Struct

Vector3 = tuple[float, float, float]
Quaternion = tuple[float, float, float, float]

IDENTITY_ROTATION: Quaternion = (0.0, 0.0, 0.0, 1.0)

RIG_FRAME = "rig"
"""The frame a rig's cameras are placed in (``CameraInfo.T_rig_camera``); world for a fixed rig."""
WORLD_FRAME = "world"
"""The frame a tracker's world-fixed results are in (rigid bodies, triangulated points): a fixed rig's frame."""


class Transform(Struct):
    """``T_parent_child``: translation (m) and rotation (unit quaternion x, y, z, w)."""

    translation: Vector3 = (0.0, 0.0, 0.0)
    rotation: Quaternion = IDENTITY_ROTATION

    @field_validator("translation")
    @classmethod
    def _finite(cls, value: Vector3) -> Vector3:
        if not all(map(math.isfinite, value)):
            raise ValueError("translation must be finite")
        return value

    @field_validator("rotation")
    @classmethod
    def _unit(cls, value: Quaternion) -> Quaternion:
        norm = math.sqrt(sum(v * v for v in value))
        if not math.isfinite(norm) or abs(norm - 1.0) > 1e-3:
            raise ValueError(f"rotation quaternion (x, y, z, w) must have unit norm, got {norm:.6g}")
        if abs(norm - 1.0) <= 4 * sys.float_info.epsilon:  # already unit: dividing again would move it
            return value
        x, y, z, w = (v / norm for v in value)
        return (x, y, z, w)


class FrameTransform(Struct):
    """A named transform ``T_parent_child`` between two frames."""

    parent_frame: str
    child_frame: str
    transform: Transform


class StaticTransforms(Message):
    """A rig's static transforms, ``T_parent_child`` each; ``header.frame_id`` is the rig frame.

    Each unordered pair of frames appears at most once and no frame is its own parent.
    """

    SCHEMA = "artrack.StaticTransforms"
    VERSION = 1

    transforms: tuple[FrameTransform, ...] = ()

    @field_validator("transforms")
    @classmethod
    def _distinct(cls, value: tuple[FrameTransform, ...]) -> tuple[FrameTransform, ...]:
        seen: set[frozenset[str]] = set()
        for edge in value:
            pair = frozenset((edge.parent_frame, edge.child_frame))
            if not edge.parent_frame or not edge.child_frame or len(pair) == 1:
                raise ValueError(f"transform {edge.parent_frame!r} <- {edge.child_frame!r} needs two named frames")
            if pair in seen:
                raise ValueError(f"frames {edge.parent_frame!r} and {edge.child_frame!r} are joined more than once")
            seen.add(pair)
        return value
