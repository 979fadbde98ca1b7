"""Camera calibration files in the ROS ``camera_info`` YAML layout, read and written.

The layout (what ``camera_calibration`` and ``camera_info_manager`` write)::

    image_width: 640
    image_height: 480
    camera_name: cam0
    camera_matrix: {rows: 3, cols: 3, data: [fx, 0, cx, 0, fy, cy, 0, 0, 1]}
    distortion_model: plumb_bob
    distortion_coefficients: {rows: 1, cols: 5, data: [k1, k2, p1, p2, k3]}
    rectification_matrix: {rows: 3, cols: 3, data: [...]}
    projection_matrix: {rows: 3, cols: 4, data: [...]}

artrack adds an optional ``T_rig_camera`` (4x4, same ``{rows, cols, data}`` form) for
cameras of a multi-camera rig.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import yaml

from services.calibration.yaml_file import read_yaml
from services.geometry.camera import CameraModel


class CalibrationError(ValueError):
    """A calibration file that cannot be used; the message names the file and the field."""


def _matrix(document: dict, field: str, rows: int, cols: int | None, path: Path | str) -> np.ndarray | None:
    """``field`` as a (rows, cols) array, (N,) when ``cols`` is None; None when the document lacks it."""
    entry = document.get(field)
    if entry is None:
        return None
    data = entry.get("data") if isinstance(entry, dict) else None
    if not isinstance(data, list) or not all(isinstance(v, int | float) for v in data):
        raise CalibrationError(f"{path}: {field}.data must be a list of numbers")
    if not np.isfinite(np.asarray(data, dtype=np.float64)).all():
        raise CalibrationError(f"{path}: {field}.data holds a value that is not finite (nan or inf)")
    if cols is None:
        return np.asarray(data, dtype=np.float64)
    if len(data) != rows * cols:
        raise CalibrationError(f"{path}: {field} needs {rows * cols} numbers, has {len(data)}")
    return np.asarray(data, dtype=np.float64).reshape(rows, cols)


def read_camera_info(path: Path) -> CameraModel:
    """Read a ROS camera_info YAML file (plumb_bob distortion) into a CameraModel."""
    document = read_yaml(path, CalibrationError)
    if not isinstance(document, dict):
        raise CalibrationError(f"{path}: not a camera_info mapping")
    return camera_from_document(document, path, Path(path).stem)


def camera_from_document(document: dict, path: Path | str, default_name: str) -> CameraModel:
    """A CameraModel from one camera_info mapping; ``path`` prefixes error messages (the file, and
    the entry within it); ``T_rig_camera`` is the identity when the mapping lacks it."""
    for field in ("image_width", "image_height"):
        if not isinstance(document.get(field), int) or document[field] <= 0:
            raise CalibrationError(f"{path}: {field} must be a positive integer")
    model = document.get("distortion_model", "plumb_bob")
    if model != "plumb_bob":
        raise CalibrationError(f"{path}: distortion_model {model!r} is not supported (plumb_bob only)")
    K = _matrix(document, "camera_matrix", 3, 3, path)
    if K is None:
        raise CalibrationError(f"{path}: missing camera_matrix")
    if K[0, 0] <= 0 or K[1, 1] <= 0 or K[2, 2] != 1.0:
        raise CalibrationError(f"{path}: camera_matrix must have fx, fy > 0 and a final 1")
    dist = _matrix(document, "distortion_coefficients", 1, None, path)
    dist = np.zeros(5) if dist is None else dist
    if len(dist) not in (0, 4, 5):
        raise CalibrationError(f"{path}: plumb_bob takes 4 or 5 distortion coefficients, has {len(dist)}")
    T = _matrix(document, "T_rig_camera", 4, 4, path)
    return CameraModel(
        name=str(document.get("camera_name") or default_name),
        width=document["image_width"], height=document["image_height"], K=K,
        dist=np.pad(dist, (0, 5 - len(dist))), T_rig_camera=np.eye(4) if T is None else T,
    )


def fit_to_image(camera: CameraModel, width: int, height: int, where: str) -> tuple[CameraModel, str | None]:
    """``camera`` for frames of ``width`` x ``height`` pixels, and a one-line note when it was changed.

    The same size: ``camera`` itself, no note. The same aspect ratio (width * calibrated height ==
    height * calibrated width): the intrinsics scaled to the frames, what resizing the image does to
    them (pixel centres at integer coordinates: ``cx' = (cx + 0.5) * s - 0.5``, ``fx' = fx * s``,
    likewise y), distortion unchanged (it acts on normalised coordinates). Another aspect ratio:
    CalibrationError naming ``where`` (the file, or the key it came on) and both sizes.
    """
    if (camera.width, camera.height) == (width, height):
        return camera, None
    sizes = f"calibrated for {camera.width}x{camera.height}, the frames are {width}x{height}"
    if width * camera.height != height * camera.width:
        raise CalibrationError(f"{where}: {sizes} (another aspect ratio): use a calibration made at "
                               f"{width}x{height}")
    sx, sy = width / camera.width, height / camera.height
    K = camera.K.copy()
    K[0, 0], K[1, 1] = camera.K[0, 0] * sx, camera.K[1, 1] * sy
    K[0, 2], K[1, 2] = (camera.K[0, 2] + 0.5) * sx - 0.5, (camera.K[1, 2] + 0.5) * sy - 0.5
    K[0, 1] = camera.K[0, 1] * sx
    note = f"{where}: {sizes}: intrinsics scaled by {sx:g} (fx, fy, cx, cy; distortion unchanged)"
    return replace(camera, width=width, height=height, K=K), note


def write_camera_info(path: Path, camera: CameraModel) -> None:
    """Write ``camera`` as a ROS camera_info YAML file."""
    Path(path).write_text(yaml.safe_dump(camera_document(camera), sort_keys=False, default_flow_style=None))


def camera_document(camera: CameraModel) -> dict:
    """``camera`` as a camera_info mapping (with ``T_rig_camera``), ready for ``yaml.safe_dump``."""
    P = np.hstack([camera.K, np.zeros((3, 1))])

    def block(M: np.ndarray) -> dict:
        M = np.atleast_2d(M)
        return {"rows": M.shape[0], "cols": M.shape[1], "data": [float(v) for v in M.ravel()]}

    return {
        "image_width": camera.width, "image_height": camera.height, "camera_name": camera.name,
        "camera_matrix": block(camera.K), "distortion_model": "plumb_bob",
        "distortion_coefficients": block(camera.dist.reshape(1, -1)),
        "rectification_matrix": block(np.eye(3)), "projection_matrix": block(P),
        "T_rig_camera": block(camera.T_rig_camera),
    }
