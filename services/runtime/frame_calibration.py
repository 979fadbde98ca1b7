"""The calibration a node follows for one camera's frames: a fixed one, or the camera's CameraInfo stream.

Shared by the nodes that work on one camera's frames (marker poses, image targets, SLAM). The runtime
holds the bus side only: the camera's CameraInfo inbox, the first frame waiting for the first CameraInfo,
the newest taken in between frames, and a fixed calibration fitted to the first frame, its note logged
and its refusal stopping the node. It knows no camera model and no calibration file: the node gives
``convert``, what a CameraInfo becomes (``services.convert.camera_model``), and its fixed calibration
as any ``FixedModel`` (a camera_info file: ``services.calibration.fixed.FixedCalibration``)::

    fixed = FixedCalibration.read(params.calib) if params.calib else None
    calibration = FrameCalibration.of_camera(node, params.camera, camera_model, fixed)
    for image in node.inputs(frames):
        calibration.fit_frame(node, image)
        work_on(image, calibration.current())
        calibration.refresh()
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Generic, Protocol, TypeVar

from protocol.sensors import CameraInfo, Image
from services.bus.pubsub import Inbox, Role
from services.runtime.node import Node, NodeError

__all__ = ["FIRST_INFO_WAIT_S", "INFO_DEPTH", "FixedModel", "FrameCalibration"]

FIRST_INFO_WAIT_S = 0.05
"""The longest the first frame waits for the camera's first CameraInfo."""
INFO_DEPTH = 100
"""CameraInfo messages kept until the next frame takes the newest (one a frame: none is ever dropped)."""

Model = TypeVar("Model")
Model_co = TypeVar("Model_co", covariant=True)


class FixedModel(Protocol[Model_co]):
    """A calibration given before start (a file's), which wins over the camera's CameraInfo."""

    @property
    def model(self) -> Model_co:
        """The model as given, for its own image size."""
        ...

    def fitted(self, width: int, height: int) -> tuple[Model_co, str | None]:
        """The model for frames of ``width`` x ``height`` pixels and a one-line note when it was changed for
        them; ValueError naming both sizes when it cannot serve them."""
        ...


class FrameCalibration(Generic[Model]):
    """The model in use for a camera's frames: the fixed one, or the one of the camera's newest CameraInfo.

    A capture node publishes a frame's CameraInfo just after the frame. The node takes in the
    CameraInfo that came meanwhile once a frame's results are out (``refresh``), so decoding it
    is off the frame's path; a change of calibration applies from the next frame on. Until a
    first CameraInfo is known, a frame waits for it, once, at most ``FIRST_INFO_WAIT_S``.
    """

    def __init__(self, infos: Inbox[CameraInfo], convert: Callable[[CameraInfo], Model],
                 fixed: FixedModel[Model] | None = None):
        self._infos = infos
        self._convert = convert
        self._fixed = fixed
        self.model: Model | None = None if fixed is None else fixed.model
        """The model known now (None until a first CameraInfo, without a fixed one); ``current`` may wait."""
        self._fitted = False
        self._waited = False

    @classmethod
    def of_camera(cls, node: Node, camera: str, convert: Callable[[CameraInfo], Model],
                  fixed: FixedModel[Model] | None = None) -> FrameCalibration[Model]:
        """``fixed`` when given, else ``convert`` of what ``node`` receives on ``camera``'s camera_info key
        (subscribed here either way)."""
        infos = node.inbox(node.keys.camera_info(camera), CameraInfo, Role.RESULT, depth=INFO_DEPTH)
        return cls(infos, convert, fixed)

    def fit_frame(self, node: Node, image: Image) -> None:
        """Hold the fixed model against the first frame's size: ``image``'s, ``(H, W[, C])``. Fitted to it
        (the note said in ``node``'s log, once), or NodeError naming both sizes when it cannot be. A
        CameraInfo from the bus is its capture node's to fit."""
        if self._fixed is None or self._fitted:
            return
        self._fitted = True
        try:
            self.model, note = self._fixed.fitted(image.data.shape[1], image.data.shape[0])
        except ValueError as exc:
            raise NodeError(str(exc)) from exc
        if note is not None:
            node.log.warning("%s", note)

    def current(self) -> Model | None:
        """The model for the frame at hand."""
        if self.model is None and self._fixed is None:
            self.refresh()
            if self.model is None and not self._waited:
                self._waited = True
                received = self._infos.recv(FIRST_INFO_WAIT_S)
                if received is not None:
                    self.model = self._convert(received.message)
        return self.model

    def refresh(self) -> None:
        """Take in the newest CameraInfo that arrived (a fixed model stays)."""
        if self._fixed is not None:
            return
        if (newest := self._infos.take_newest()) is not None:
            self.model = self._convert(newest.message)
