"""Rigid transforms as they travel: translation in metres, rotation as a unit quaternion.

A ``Transform`` named ``T_a_b`` maps coordinates in frame b to frame a
(``p_a = R @ p_b + t``). The quaternion is ``(x, y, z, w)``; it is normalised on
validation and refused when its norm is far from 1 (a sign of a wrong field order or
garbage). Conversions to matrices live in ``services.geometry``; the protocol holds data only.
"""

from __future__ import annotations

import math
import sys

from pydantic import field_validator

from protocol.message import Struct

Vector3 = tuple[float, float, float]
Quaternion = tuple[float, float, float, float]

IDENTITY_ROTATION: Quaternion = (0.0, 0.0, 0.0, 1.0)


class Transform(Struct):
    """``T_parent_child``: translation (m) and rotation (unit quaternion x, y, z, w)."""

    translation: Vector3 = (0.0, 0.0, 0.0)
    rotation: Quaternion = IDENTITY_ROTATION

    @field_validator("translation")
    @classmethod
    def _finite(cls, value: Vector3) -> Vector3:
        if not all(math.isfinite(v) for v in value):
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
