"""The calibration a node uses for a camera's frames: a fixed camera_info file, or the camera's CameraInfo stream.

Shared by the nodes that work on one camera's frames (marker poses, image targets, SLAM).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Protocol

from protocol.sensors import CameraInfo, Image
from services.bus.pubsub import Inbox, Role
from services.calibration.camera_info import CalibrationError, fit_to_image, read_camera_info
from services.convert import camera_model
from services.geometry.camera import CameraModel
from services.runtime.kind import FrameSizes
from services.runtime.node import Node, NodeError

FIRST_INFO_WAIT_S = 0.05
"""The longest the first frame waits for the camera's first CameraInfo."""
INFO_DEPTH = 100
"""CameraInfo messages kept until the next frame takes the newest (one a frame: none is ever dropped)."""


class FrameCalibration:
    """The camera model in use: a fixed file, or the newest CameraInfo of the camera.

    A capture node publishes a frame's CameraInfo just after the frame. The node takes in the
    CameraInfo that came meanwhile once a frame's results are out (``refresh``), so decoding it
    is off the frame's path; a change of calibration applies from the
    next frame on. Until a first CameraInfo is known, a frame waits for it, once, at most
    ``FIRST_INFO_WAIT_S``.
    """

    def __init__(self, infos: Inbox[CameraInfo], fixed: CameraModel | None, where: str = ""):
        self._infos = infos
        self.model = fixed
        self._fixed = fixed is not None
        self._where = where
        self._fitted = False
        self._waited = False

    @classmethod
    def of_camera(cls, node: Node, camera: str, fixed: CameraModel | None, where: str = "") -> FrameCalibration:
        """``fixed`` (read from the file ``where``) when given, else what ``node`` receives on ``camera``'s
        camera_info key (subscribed here)."""
        infos = node.inbox(node.keys.camera_info(camera), CameraInfo, Role.RESULT, depth=INFO_DEPTH)
        return cls(infos, fixed, where)

    def fit(self, width: int, height: int) -> str | None:
        """Hold a fixed file's model against the first frame's size: scaled to it when only the size
        differs (the note saying so is returned, once); CalibrationError naming the file and both sizes
        when the aspect ratio does too. A CameraInfo from the bus is its capture node's to fit."""
        if not self._fixed or self._fitted or self.model is None:
            return None
        self._fitted = True
        self.model, note = fit_to_image(self.model, width, height, self._where)
        return note

    def fit_frame(self, node: Node, image: Image) -> None:
        """``fit`` to ``image``'s size, the note said in ``node``'s log; NodeError when the file cannot fit."""
        try:
            note = self.fit(image.data.shape[1], image.data.shape[0])
        except CalibrationError as exc:
            raise NodeError(str(exc)) from exc
        if note is not None:
            node.log.warning("%s", note)

    def current(self) -> CameraModel | None:
        """The model for the frame at hand."""
        if self.model is None and not self._fixed:
            self.refresh()
            if self.model is None and not self._waited:
                self._waited = True
                received = self._infos.recv(FIRST_INFO_WAIT_S)
                if received is not None:
                    self.model = camera_model(received.message)
        return self.model

    def refresh(self) -> None:
        """Take in the newest CameraInfo that arrived (a fixed file stays)."""
        if self._fixed:
            return
        newest = None
        while (received := self._infos.take()) is not None:
            newest = received.message
        if newest is not None:
            self.model = camera_model(newest)


class OwnCalibration(Protocol):
    """The parameters of a node of one camera that may bring a calibration file of its own."""

    @property
    def camera(self) -> str: ...

    @property
    def calib(self) -> Path | None: ...


def check_own_calibration(params: OwnCalibration, sizes: Callable[[], FrameSizes]) -> None:
    """What ``FrameCalibration.fit`` would stop the node for at its first frame, told before start (a node kind's
    ``check_frames``): CalibrationError naming the file and both sizes when ``params.calib`` has another aspect
    ratio than the frames of ``params.camera``, whose size ``sizes()`` gives when the source tells it."""
    if params.calib is None:
        return
    size = sizes().get(params.camera)
    if size is not None:
        fit_to_image(read_camera_info(params.calib), *size, str(params.calib))
