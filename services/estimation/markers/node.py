"""Marker pose node: one camera's markers -> ``T_camera_marker`` (and board) poses.

Inputs: the camera's ``image`` key (``input = "images"``: markers are detected here, in this
process, and the detections published on the camera's ``markers`` key too) or its
``markers`` key (``input = "detections"``: a separate ``markers`` node detects), plus its
``camera_info`` key (the newest one, taken in between frames; a ``calib`` file given here wins).

Outputs, each with the header of the frame the detections came from:

* ``pose/<camera>/marker/<id>``: ``T_<camera>_marker/<id>`` per marker with a side length,
  state ``tracking``, with reprojection RMS, corner count, ambiguity flag and a 6x6
  covariance; a marker tracked in the previous frame and not seen in this one gets one
  ``lost`` pose (identity transform).
* ``pose/<camera>/<board>``: the board's pose from all its visible markers at once, when a
  board file is given; the board's own markers get no pose of their own.
* Without calibration (no CameraInfo yet and no file): one pose per detected marker in state
  ``no_calibration`` (identity transform) and a ``no_calibration`` report, instead of poses.
* ``<camera>/overlay`` (with ``overlay`` set, ``input = "images"`` only): every frame, as
  bgr8, with a wireframe cube and axes drawn on each target that got a pose in it
  (``services.estimation.overlay``; a frame with none, or without calibration, goes out
  undrawn), while anything subscribes to the key (no frame is drawn while nothing does). A
  marker's cube has the marker's side; a board's is half the smaller side of its markers'
  bounding box, at least its largest marker (``overlay.board_cube_size``: the axis length of
  OpenCV's board samples, a cube that stays on the board). The header is the
  frame's, except ``frame_id`` = ``<frame's frame_id>/overlay``: a frame id names a camera's
  picture to viewers, and Rerun keeps one image per entity, so the overlay under the
  camera's own frame id would overwrite the camera's image there; under its own it is a
  picture of its own (``world/<camera>/overlay/image``, its own 2D view). Role FRAME
  (latest-wins); it costs a 3-channel copy of every frame on the bus, so it is off by
  default. With ``input = "detections"`` the node sees no frames and the option is refused.

Markers that give no pose (degenerate corners, no side length, not converged, ...) are counted
by reason (``services.estimation.markers.pose.SkipReason``, its values as kinds) in the node's ``skipped`` statistics
and reported on its errors key; nothing raises.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Annotated, ClassVar, Literal

import numpy as np
from pydantic import Field, model_validator

from protocol.detections import MarkerDetections
from protocol.keys import KeyName
from protocol.message import Header
from protocol.poses import Pose, PoseQuality
from protocol.sensors import Image
from protocol.tracking_state import TrackingState
from services.bus.pubsub import Inbox, Publisher, Role
from services.calibration.fixed import FixedCalibration, check_own_calibration
from services.convert import CameraModels, pose_message
from services.detection.markers.detector import MarkerDetector
from services.detection.markers.node import as_message
from services.detection.markers.settings import DetectorSettings
from services.estimation.markers.map import MarkerMap, load_marker_map
from services.estimation.markers.pose import FrameEstimate, MarkerPoseEstimator, MarkerPoseOptions
from services.estimation.markers.tracking import TargetTracks, marker_detector
from services.estimation.overlay import OverlayTarget, board_cube_size, draw_overlay, to_bgr8
from services.geometry.camera import CameraModel
from services.runtime.frame_calibration import FrameCalibration
from services.runtime.kind import NodeKind
from services.runtime.node import Node, NodeError
from services.runtime.params import Flat, NodeParams


class Params(NodeParams):
    """Which camera, where its markers come from, and how poses are estimated; the detector's
    tuning and ``corner_sigma_px`` may change while the node runs."""

    RELOADABLE: ClassVar[frozenset[str]] = DetectorSettings.TUNING | {"corner_sigma_px"}

    detection: Annotated[DetectorSettings, Flat()] = DetectorSettings()
    camera: KeyName = "cam0"
    input: Literal["images", "detections"] = Field(
        default="images", description="detect here from images, or take a markers node's detections")
    board: Path | None = Field(default=None, description="board / marker map YAML: one pose for all its markers")
    pose: Annotated[MarkerPoseOptions, Flat()] = MarkerPoseOptions()
    calib: Path | None = Field(default=None, description="ROS camera_info YAML; default: the camera's CameraInfo")
    depth: int = Field(default=2, ge=1, le=1000, description="frames queued while busy (images input; as the "
                                                             "markers node's: one waits, more are dropped)")
    overlay: bool = Field(default=False, description="publish the frames with a cube and axes drawn on each "
                                                     "tracked marker/board (images input)")

    @model_validator(mode="after")
    def _overlay_needs_frames(self) -> Params:
        if self.overlay and self.input != "images":
            raise ValueError(f"overlay draws on the camera's frames: it needs input 'images' (with input "
                             f"{self.input!r} this node never sees a frame)")
        return self


class PosePublishers:
    """One publisher per target, created when the target first appears; remembers who was tracked.

    A frame's poses are all built before the first is sent, so they leave back to back, Zenoh
    batches them, and each subscriber wakes once for the frame rather than once for each pose.
    """

    def __init__(self, node: Node, camera: str):
        self._node = node
        self._camera = camera
        self._publishers: dict[str, Publisher[Pose]] = {}
        self._tracks = TargetTracks()

    def publish(self, poses: list[Pose]) -> None:
        """Send ``poses`` (one frame's), each on its target's key."""
        for pose in poses:
            child = pose.child_frame_id
            if child not in self._publishers:
                key = self._node.keys.pose(f"{self._camera}/{child}")
                self._publishers[child] = self._node.publisher(key, Pose, Role.RESULT)
            self._publishers[child].put(pose)

    def frame(self, header: Header, tracking: list[Pose]) -> None:
        """Send one frame's ``tracking`` poses, plus one ``lost`` pose for each target tracked in the
        previous frame and not in this one."""
        lost = [Pose(header=header, child_frame_id=child, state=TrackingState.LOST)
                for child in self._tracks.update(pose.child_frame_id for pose in tracking)]
        self.publish(tracking + lost)


class _Overlay:
    """Publishes each frame with a cube and axes drawn on every target posed in it (see the module docstring)."""

    def __init__(self, node: Node, camera: str, board: MarkerMap | None):
        self._camera = camera
        self._out = node.publisher(node.keys.overlay(camera), Image, Role.FRAME)
        self._board = board.name if board else None
        self._board_size = 0.0
        if board is not None and board.markers:
            corners = np.concatenate([marker.corners() for marker in board.markers.values()])
            self._board_size = board_cube_size(corners, max(marker.length for marker in board.markers.values()))

    def put(self, image: Image, detections: MarkerDetections, camera: CameraModel | None,
            result: FrameEstimate | None) -> None:
        """Draw and publish ``image`` with ``result``'s targets; nothing while no one subscribes to the overlay."""
        if not self._out.matched():
            return
        sides = dict(zip(detections.ids.tolist(), detections.side_m.tolist(), strict=True))
        targets = []
        for estimate in result.poses if result is not None else ():
            size = self._board_size if estimate.target == self._board else sides.get(estimate.marker_ids[0], 0.0)
            if size > 0:
                targets.append(OverlayTarget(estimate.T, size, estimate.target))
        if camera is not None and targets:
            drawn = draw_overlay(image.data, camera.K, camera.dist, targets)
        else:
            drawn = to_bgr8(image.data)
        header = image.header.model_copy(update={"frame_id": f"{image.header.frame_id or self._camera}/overlay"})
        self._out.put(Image(header=header, encoding="bgr8", data=drawn))


def _prepare(params: Params) -> tuple[MarkerMap | None, FixedCalibration | None, MarkerDetector | None]:
    """The board, fixed calibration and detector ``params`` name; ValueError (one line) when one cannot be
    had, or when detecting here with no side length at all (every marker would fail to give a pose)."""
    detection = params.detection
    if params.input == "images" and detection.marker_length is None and not detection.lengths and params.board is None:
        raise ValueError("no marker side length, so no pose could be given: marker_length is needed (artrack run: "
                         "--marker-length METRES, > 0), or lengths of single ids, or a board")
    board = load_marker_map(params.board) if params.board else None
    fixed = FixedCalibration.read(params.calib) if params.calib else None
    detector = marker_detector(detection, board) if params.input == "images" else None
    return board, fixed, detector


def _check(params: Params) -> None:
    _prepare(params)


def run(node: Node, params: Params) -> None:
    try:
        board, fixed, detector = _prepare(params)
    except ValueError as exc:
        raise NodeError(str(exc)) from exc
    estimator = MarkerPoseEstimator(params.pose, board)
    live: dict[str, MarkerDetector] = {} if detector is None else {"detector": detector}

    def apply(new: Params) -> None:
        """Put a live change to work: the covariance's corner noise, and the detector's tuning."""
        if detector is None and new.detection.tuning() != params.detection.tuning():
            raise ValueError("this node takes a markers node's detections: change that node's detector")
        if detector is not None:
            live["detector"] = marker_detector(new.detection, board)
        estimator.options = new.pose

    node.configurable(params, apply)
    keys = node.keys
    calibration = FrameCalibration.of_camera(node, params.camera, CameraModels(), fixed)
    poses = PosePublishers(node, params.camera)
    overlay = _Overlay(node, params.camera, board) if params.overlay else None
    found: Iterator[tuple[Image | None, MarkerDetections]]
    if detector is None:
        found = ((None, d) for d in node.inputs(node.inbox(keys.markers(params.camera), MarkerDetections,
                                                            Role.RESULT)))
    else:
        frames = node.inbox(keys.image(params.camera), Image, Role.FRAME, depth=params.depth)
        found = _detected(node, frames, live, params.detection.dictionary_name(board.dictionary if board else None),
                          node.publisher(keys.markers(params.camera), MarkerDetections), calibration)
    for image, detections in found:
        camera = calibration.current()
        result = _estimate(node, detections, camera, estimator, poses)
        if overlay is not None and image is not None:
            overlay.put(image, detections, camera, result)
        calibration.refresh()


def _detected(node: Node, frames: Inbox[Image], live: dict[str, MarkerDetector], dictionary: str,
              out: Publisher[MarkerDetections],
              calibration: FrameCalibration[CameraModel]) -> Iterator[tuple[Image, MarkerDetections]]:
    """Each frame from ``frames`` with its detections by ``live["detector"]`` (replaced by live
    changes; given the calibration known so far, if any, for its corner refinement), published on
    ``out`` once the frame's poses are out: the detections are a side output, and the poses
    should not wait for them."""
    for image in node.inputs(frames):
        calibration.fit_frame(node, image)
        camera = calibration.model  # known now: the first frame does not wait for a CameraInfo to detect
        lens = (camera.K, camera.dist) if camera is not None else (None, None)
        detections = as_message(image.header, dictionary, live["detector"].detect(image.data, *lens))
        yield image, detections
        out.put(detections)


def _estimate(node: Node, detections: MarkerDetections, camera: CameraModel | None,
              estimator: MarkerPoseEstimator, poses: PosePublishers) -> FrameEstimate | None:
    """Publish the poses of ``detections``; the estimate, None without calibration."""
    header = detections.header
    if camera is None:
        poses.publish([Pose(header=header, child_frame_id=f"marker/{marker}", state=TrackingState.NO_CALIBRATION,
                            quality=PoseQuality(inliers=4)) for marker in detections.ids])
        if len(detections.ids):
            node.report("no_calibration", f"no CameraInfo for {header.frame_id or 'the camera'} and no calib file: "
                        "detections only", node.keys.camera_info(header.frame_id))
        return None
    result = estimator.estimate(detections.ids, detections.corners, detections.side_m, camera.K, camera.dist)
    for reason, count in result.failures.items():
        kind = reason.value
        node.report(kind, f"frame {header.seq}: {count} marker(s) gave no pose ({kind.replace('_', ' ')})",
                    node.keys.markers(header.frame_id), count)
    poses.frame(header, [pose_message(header, estimate.target, estimate.T, rms_px=estimate.rms_px,
                                      inliers=estimate.points, ambiguous=estimate.ambiguous,
                                      covariance=estimate.covariance) for estimate in result.poses])
    return result


def _inputs(params: Params) -> tuple[str, ...]:
    stream = "image" if params.input == "images" else "markers"
    return (f"{params.camera}/{stream}", f"{params.camera}/camera_info")


def _outputs(params: Params) -> tuple[str, ...]:
    extra = (f"{params.camera}/markers",) if params.input == "images" else ()
    return (f"pose/{params.camera}/**", *extra, *((f"{params.camera}/overlay",) if params.overlay else ()))


KIND = NodeKind(name="marker_pose",
                summary="marker and board poses from a camera's frames (or a markers node's detections)",
                params=Params, run=run, inputs=_inputs, outputs=_outputs, check=_check,
                check_frames=check_own_calibration)
