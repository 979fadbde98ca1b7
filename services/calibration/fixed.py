"""A fixed calibration: the camera_info file a node of one camera brings instead of the camera's CameraInfo stream.

Pure calibration, no bus: the file read (``FixedCalibration.read``), its model fitted to a frame size
(``FixedCalibration.fitted``, ``services.calibration.camera_info.fit_to_image``), and the look a node kind
takes before start (``check_own_calibration``). Which of the file and the stream a frame uses, and the
stream itself, is the runtime's (``services.runtime.frame_calibration.FrameCalibration``, for which a
``FixedCalibration`` is a ``FixedModel``); a node composes the two::

    fixed = FixedCalibration.read(params.calib) if params.calib else None
    calibration = FrameCalibration.of_camera(node, params.camera, camera_model, fixed)
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

from services.calibration.camera_info import fit_to_image, read_camera_info
from services.geometry.camera import CameraModel

__all__ = ["FixedCalibration", "OwnCalibration", "check_own_calibration"]


@dataclass(frozen=True)
class FixedCalibration:
    """The camera model of the camera_info file ``path``, for the image size it was made at."""

    path: Path
    model: CameraModel

    @classmethod
    def read(cls, path: Path) -> FixedCalibration:
        """The file at ``path``; CalibrationError naming the file and the field when it cannot be used."""
        return cls(path, read_camera_info(path))

    def fitted(self, width: int, height: int) -> tuple[CameraModel, str | None]:
        """``model`` for frames of ``width`` x ``height`` pixels, and a one-line note when it was scaled to them
        (the same aspect ratio); CalibrationError naming the file and both sizes for another aspect ratio."""
        return fit_to_image(self.model, width, height, str(self.path))


class OwnCalibration(Protocol):
    """The parameters of a node of one camera that may bring a calibration file of its own."""

    @property
    def camera(self) -> str: ...

    @property
    def calib(self) -> Path | None: ...


def check_own_calibration(params: OwnCalibration, sizes: Callable[[], Mapping[str, tuple[int, int]]]) -> None:
    """What fitting ``params.calib`` would stop the node for at its first frame, told before start (a node kind's
    ``check_frames``): CalibrationError naming the file and both sizes when the file has another aspect ratio
    than the frames of ``params.camera``, whose ``(width, height)`` ``sizes()`` gives when the source tells it."""
    if params.calib is None:
        return
    size = sizes().get(params.camera)
    if size is not None:
        FixedCalibration.read(params.calib).fitted(*size)
