"""Camera messages: images and their calibration.

``Image.data`` is the pixel array exactly as OpenCV holds it: ``(H, W)`` for mono,
``(H, W, 3)`` BGR or ``(H, W, 4)`` BGRA, uint8 or uint16, row-major. ``CameraInfo`` carries
the fields of ROS ``sensor_msgs/CameraInfo`` (same names, same row-major layouts), plus the
camera's pose in its rig for multi-camera set-ups.
"""

from __future__ import annotations

from typing import Annotated, Literal

import numpy as np
from pydantic import Field, model_validator

from protocol.arrays import array_field, dtype_name
from protocol.message import Message, Struct
from protocol.spatial import Transform

ImageEncoding = Literal["mono8", "mono16", "bgr8", "bgra8"]

_LAYOUT: dict[str, tuple[str, int]] = {
    "mono8": ("uint8", 1),
    "mono16": ("uint16", 1),
    "bgr8": ("uint8", 3),
    "bgra8": ("uint8", 4),
}


class Image(Message):
    """One camera frame; ``header.frame_id`` is the camera's optical frame (OpenCV axes)."""

    SCHEMA = "artrack.Image"
    VERSION = 1

    encoding: ImageEncoding
    data: Annotated[np.ndarray, array_field(("uint8", "uint16"), (None, None), (None, None, 3), (None, None, 4))]

    @model_validator(mode="after")
    def _layout_matches(self) -> Image:
        dtype, channels = _LAYOUT[self.encoding]
        found = 1 if self.data.ndim == 2 else self.data.shape[2]
        if dtype_name(self.data.dtype) != dtype or found != channels:
            raise ValueError(
                f"encoding {self.encoding} needs {dtype} with {channels} channel(s), "
                f"got {self.data.dtype} with {found}"
            )
        return self

    @property
    def height(self) -> int:
        return int(self.data.shape[0])

    @property
    def width(self) -> int:
        return int(self.data.shape[1])


class RegionOfInterest(Struct):
    """ROS ``RegionOfInterest``: the sub-window of the full sensor this calibration covers."""

    x_offset: int = Field(default=0, ge=0)
    y_offset: int = Field(default=0, ge=0)
    height: int = Field(default=0, ge=0)
    width: int = Field(default=0, ge=0)
    do_rectify: bool = False


DistortionModel = Literal["plumb_bob", "rational_polynomial", "equidistant"]

_IDENTITY_3x3 = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)


class CameraInfo(Message):
    """Intrinsic calibration of one camera, ROS ``camera_info`` layout.

    ``k`` is the 3x3 camera matrix, ``r`` the rectification rotation and ``p`` the 3x4
    projection, all row-major. ``d`` holds the distortion coefficients in OpenCV's order
    (k1, k2, p1, p2[, k3[, k4, k5, k6]]) for ``plumb_bob``/``rational_polynomial``, and
    (k1, k2, k3, k4) for ``equidistant``. ``T_rig_camera`` places the camera in its rig
    (identity for a single camera).
    """

    SCHEMA = "artrack.CameraInfo"
    VERSION = 1

    width: int = Field(gt=0)
    height: int = Field(gt=0)
    distortion_model: DistortionModel = "plumb_bob"
    d: tuple[float, ...] = ()
    k: tuple[float, float, float, float, float, float, float, float, float]
    r: tuple[float, float, float, float, float, float, float, float, float] = _IDENTITY_3x3
    p: tuple[float, float, float, float, float, float, float, float, float, float, float, float] | None = None
    binning_x: int = Field(default=0, ge=0)
    binning_y: int = Field(default=0, ge=0)
    roi: RegionOfInterest = RegionOfInterest()
    T_rig_camera: Transform = Transform()

    @model_validator(mode="after")
    def _sane(self) -> CameraInfo:
        fx, _, cx, _, fy, cy, _, _, one = self.k
        if fx <= 0 or fy <= 0 or one != 1.0:
            raise ValueError("k must be an upper-triangular camera matrix with fx, fy > 0 and k[8] = 1")
        allowed = {"plumb_bob": (0, 4, 5), "rational_polynomial": (8,), "equidistant": (4,)}
        if len(self.d) not in allowed[self.distortion_model]:
            raise ValueError(
                f"{self.distortion_model} takes {' or '.join(map(str, allowed[self.distortion_model]))} "
                f"distortion coefficients, got {len(self.d)}"
            )
        return self
