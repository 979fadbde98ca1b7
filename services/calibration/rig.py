"""A calibrated multi-camera rig: named cameras with intrinsics and their poses in the rig frame.

The rig file (see docs/rig-file.md) is YAML: an optional ``rig`` name and a ``cameras`` list,
each entry one camera in the ROS ``camera_info`` layout (``services.calibration.camera_info``)
with a required ``T_rig_camera``: ``{rows: 4, cols: 4, data: [16 numbers, row-major]}``, the
camera's pose in the rig frame (maps camera coordinates into the rig frame).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import yaml

from services.calibration.camera_info import CalibrationError, camera_document, camera_from_document
from services.calibration.yaml_file import read_yaml
from services.geometry.camera import CameraModel
from services.geometry.se3 import check_transform

__all__ = ["Rig", "read_rig", "write_rig", "RIGID_TOLERANCE"]

RIGID_TOLERANCE = 1e-6
"""Largest deviation of ``T_rig_camera``'s rotation block from orthonormal (and of det from 1)."""


@dataclass(frozen=True)
class Rig:
    """``cameras``: two or more CameraModel with distinct names; each ``T_rig_camera`` (4, 4) is
    the camera's pose in the rig frame (for a tracker, the rig frame is the world)."""

    name: str
    cameras: tuple[CameraModel, ...]

    def __post_init__(self) -> None:
        if len(self.cameras) < 2:
            raise ValueError(f"rig {self.name!r}: needs at least 2 cameras, has {len(self.cameras)}")
        names = [c.name for c in self.cameras]
        if len(set(names)) != len(names):
            raise ValueError(f"rig {self.name!r}: camera names must be distinct, got {names}")
        for camera in self.cameras:
            check_transform(camera.T_rig_camera, f"rig {self.name!r}: camera {camera.name!r} T_rig_camera",
                            RIGID_TOLERANCE)

    def camera(self, name: str) -> CameraModel:
        """The camera called ``name``; KeyError listing the rig's cameras otherwise."""
        for camera in self.cameras:
            if camera.name == name:
                return camera
        raise KeyError(f"rig {self.name!r} has no camera {name!r}; it has {', '.join(self.names)}")

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(c.name for c in self.cameras)


def read_rig(path: Path) -> Rig:
    """The rig of a rig YAML file; CalibrationError (one line naming the file) for a file that
    cannot be read, fewer than two cameras, a camera without ``T_rig_camera``, or a non-rigid one."""
    document = read_yaml(path, CalibrationError)
    if not isinstance(document, dict) or not isinstance(document.get("cameras"), list):
        raise CalibrationError(f"{path}: a rig file is a mapping with a 'cameras' list")
    entries = document["cameras"]
    if len(entries) < 2:
        raise CalibrationError(f"{path}: a rig needs at least 2 cameras, the file has {len(entries)}")
    cameras = []
    for i, entry in enumerate(entries):
        where = f"{path}: cameras[{i}]"
        if not isinstance(entry, dict):
            raise CalibrationError(f"{where}: not a camera_info mapping")
        if "T_rig_camera" not in entry:
            raise CalibrationError(f"{where} ({entry.get('camera_name', 'unnamed')}): missing T_rig_camera "
                                   "(the camera's extrinsics in the rig frame)")
        camera = camera_from_document(entry, where, f"cam{i}")
        try:
            check_transform(camera.T_rig_camera, "T_rig_camera", RIGID_TOLERANCE)
        except ValueError as exc:
            raise CalibrationError(f"{where} ({camera.name}): {exc}") from exc
        cameras.append(camera)
    name = str(document.get("rig") or Path(path).stem)
    try:
        return Rig(name, tuple(cameras))
    except ValueError as exc:
        raise CalibrationError(f"{path}: {exc}") from exc


def write_rig(path: Path, rig: Rig) -> None:
    """Write ``rig`` as a rig YAML file that ``read_rig`` reads back."""
    document = {"rig": rig.name, "cameras": [camera_document(c) for c in rig.cameras]}
    Path(path).write_text(yaml.safe_dump(document, sort_keys=False, default_flow_style=None))
