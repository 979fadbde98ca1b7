"""KITTI odometry calibration: ``calib.txt`` beside the ``image_<i>/`` folders of a sequence.

Each camera ``i`` has a line ``P<i>: p00 p01 ... p23``, the row-major (3, 4) projection matrix of its
rectified images in the frame of camera 0 (``P_i = K_i [R_i | t_i]``; KITTI's rectified cameras share one
orientation, so ``R_i`` is the identity and ``t_i`` their offset along the baseline). Other named lines
(``Tr:``, the lidar's transform) are left alone. Some copies drop the names: lines of 12 bare numbers are
``P0``, ``P1``, ... in order. The images are rectified: no distortion.
"""

from __future__ import annotations

import re
from pathlib import Path

import cv2
import numpy as np

from services.calibration.camera_info import CalibrationError
from services.geometry.camera import CameraModel
from services.geometry.se3 import make_transform

CALIB_FILE = "calib.txt"
FOLDER = re.compile(r"image_(\d+)")
"""A KITTI camera folder's name: ``image_<i>`` holds the frames of camera ``i``."""


def read_projections(path: Path) -> dict[int, np.ndarray]:
    """The (3, 4) float64 projection matrix of each camera ``i`` that ``path`` has a line for (``P<i>:`` or bare);
    CalibrationError naming the file and line when one does not hold 12 finite numbers."""
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise CalibrationError(f"cannot read {path}: {getattr(exc, 'strerror', None) or exc}") from exc
    found: dict[int, np.ndarray] = {}
    unnamed = 0
    for number, line in enumerate(text.splitlines(), 1):
        name, colon, values = line.partition(":")
        if not colon and len(line.split()) == 12:
            name, values, unnamed = f"P{unnamed}", line, unnamed + 1
        elif not colon or not re.fullmatch(r"P\d+", name.strip()):
            continue
        try:
            P = np.array([float(v) for v in values.split()], dtype=np.float64)
        except ValueError:
            P = np.empty(0)
        if P.size != 12 or not np.isfinite(P).all():
            raise CalibrationError(f"{path}:{number}: {name.strip()} needs 12 finite numbers (row-major 3x4)")
        found[int(name.strip()[1:])] = P.reshape(3, 4)
    return found


def camera_from_projection(name: str, P: np.ndarray, width: int, height: int) -> CameraModel:
    """The camera of projection matrix ``P`` (3, 4) (``cv2.decomposeProjectionMatrix``): K, and
    ``T_rig_camera`` with the rig the frame ``P`` projects from; no distortion."""
    K, R, centre = cv2.decomposeProjectionMatrix(P)[:3]
    K = K / K[2, 2]
    C = centre[:3, 0] / centre[3, 0]
    return CameraModel(name, width, height, K, np.zeros(5), make_transform(R.T, C))


def folder_camera(folder: Path, name: str, width: int, height: int) -> CameraModel | None:
    """The camera of the KITTI folder ``folder`` (``image_<i>``) from ``calib.txt`` beside it (in its parent, or
    in it), named ``name``; None when the folder is not so named or no such file has its ``P<i>`` line."""
    match = FOLDER.fullmatch(folder.name)
    if match is None:
        return None
    for path in (folder.parent / CALIB_FILE, folder / CALIB_FILE):
        if path.is_file():
            P = read_projections(path).get(int(match.group(1)))
            return None if P is None else camera_from_projection(name, P, width, height)
    return None
