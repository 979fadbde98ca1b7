"""Image targets as a tracker describes them: what each target it poses is, in the frame its poses place.

A features node (natural-feature tracker) tracks printed images in one camera's frames and publishes each
one's ``T_camera_target`` as a ``protocol.poses.Pose`` with child frame ``target/<name>``. The pose alone
says where that frame is, not what is drawn in it; ``ImageTargets`` says it: each target's printed size
and where its image lies in the target frame. It is static data: published before the node's first
poses and answered on request for a subscriber that comes later (``protocol.keys.Keys.targets``).
"""

from __future__ import annotations

import math

from pydantic import Field, field_validator, model_validator

from protocol.message import Message, Struct
from protocol.spatial import Vector3

Corners = tuple[Vector3, Vector3, Vector3, Vector3]

SIZE_TOLERANCE = 1e-6
"""Relative tolerance within which ``corners`` must span ``width_m`` by ``height_m`` at a right angle."""


def _minus(a: Vector3, b: Vector3) -> Vector3:
    return a[0] - b[0], a[1] - b[1], a[2] - b[2]


def _dot(a: Vector3, b: Vector3) -> float:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


class ImageTarget(Struct):
    """One printed image target.

    ``name``: its name in the target library; ``frame_id``: the child frame of its poses
    (``target/<name>``); ``width_m``, ``height_m``: the printed image's size, metres; ``corners``: the
    image's outer corners in that frame (x, y, z metres), top-left, top-right, bottom-right, bottom-left
    as the image is seen upright. The corners say where the frame's origin and axes are: artrack's
    targets have the origin at the image's centre, x right, y up and z out of the image towards the
    viewer (the ArUco marker frame), so their corners are (-w/2, h/2, 0), (w/2, h/2, 0),
    (w/2, -h/2, 0), (-w/2, -h/2, 0). Top-left to top-right must be ``width_m`` long, top-left to
    bottom-left ``height_m``, at a right angle, and the four must close a rectangle.
    """

    name: str = Field(min_length=1)
    frame_id: str = Field(min_length=1)
    width_m: float = Field(gt=0)
    height_m: float = Field(gt=0)
    corners: Corners

    @model_validator(mode="after")
    def _rectangle(self) -> ImageTarget:
        top_left, top_right, bottom_right, bottom_left = self.corners
        across, down = _minus(top_right, top_left), _minus(bottom_left, top_left)
        closing = _minus(_minus(bottom_right, bottom_left), across)
        width, height = math.sqrt(_dot(across, across)), math.sqrt(_dot(down, down))
        scale = max(self.width_m, self.height_m)
        if not (math.isclose(width, self.width_m, rel_tol=SIZE_TOLERANCE)
                and math.isclose(height, self.height_m, rel_tol=SIZE_TOLERANCE)):
            raise ValueError(f"target {self.name!r}: corners span {width:.6g} x {height:.6g} m, not its "
                             f"{self.width_m:.6g} x {self.height_m:.6g} m")
        if abs(_dot(across, down)) > SIZE_TOLERANCE * scale * scale or any(
                abs(v) > SIZE_TOLERANCE * scale for v in closing):
            raise ValueError(f"target {self.name!r}: corners do not make a rectangle (top-left, top-right, "
                             "bottom-right, bottom-left)")
        return self


class ImageTargets(Message):
    """Every image target one tracker poses in a camera's frames; ``header.frame_id`` is that camera's frame
    (the parent of the targets' poses). Names are unique."""

    SCHEMA = "artrack.ImageTargets"
    VERSION = 1

    targets: tuple[ImageTarget, ...] = ()

    @field_validator("targets")
    @classmethod
    def _distinct(cls, value: tuple[ImageTarget, ...]) -> tuple[ImageTarget, ...]:
        names = [target.name for target in value]
        twice = sorted({name for name in names if names.count(name) > 1})
        if twice:
            raise ValueError(f"target {twice[0]!r} is described more than once")
        return value
