"""Features node: one camera's frames -> the pose of each image target (``T_camera_target``).

Inputs: the camera's ``image`` key and its ``camera_info`` key (the newest CameraInfo, taken in
between frames: ``services.runtime.frame_calibration``; a ``calib`` file given here wins, scaled to the
frames when only their size differs and refused when their aspect ratio does too:
``services.calibration.fixed``).

Targets: ``target`` names them, each a target of the library in ``targets`` (default
``$XDG_DATA_HOME/artrack/targets``, see ``services.estimation.targets.library``; ``artrack run``
gives a synthetic ``planar_target`` source's own, in a library of its own). A name the library
does not hold is refused before the node starts (``check``), in one line naming the library folder.

Per frame, one ``TargetTracker`` per target (``services.estimation.targets.tracking``), all
through ``track_targets``, so the frame is made grey once and its keypoints are extracted at most
once, only when a target needs recognition. Each target gets one ``Pose`` per frame on
``pose/<camera>/target/<name>`` (child frame ``target/<name>``), with the frame's header:

* state ``recognised`` (found from scratch) or ``tracking`` (followed on from the previous
  frame), the transform, quality (``inliers``: the points the pose rests on;
  ``reprojection_rms_px``: their RMS residual, undistorted pixels) and the 6x6 covariance over
  (tx, ty, tz, rx, ry, rz) in the target frame (metres, radians);
* state ``lost`` (identity transform) with ``reason``: recognition's state (``no_features``,
  ``too_few_matches``, ...), ``unusable_frame`` for a frame the tracker cannot read, or
  ``no_calibration`` before the camera has one. ``no_features`` (a frame without a keypoint: flat,
  black, out of focus), ``unusable_frame`` and ``no_calibration`` are counted among the node's
  skipped inputs (once per frame) and reported on its errors key; a target merely out of view is
  not. Frames may be ``mono8``, ``mono16`` or ``bgr8`` (made grey once); another layout is an
  ``unusable_frame``.

Why the node extracts keypoints itself, on demand, rather than joining a ``keypoints`` node's
output by ``seq`` (``Node.synced``): a tracked frame needs no keypoints at all (Lucas-Kanade
follows the points of the previous frame), only a frame that falls back to recognition does. A
``keypoints`` node would describe every frame (its cost per frame: docs/benchmarks.md) and send
its descriptors over the bus, and this node would wait for them before it could even start
following points: more CPU on a 2-core machine and a hop more of latency on every frame, for
keypoints that are thrown away on nearly all of them. Extracted here they also come from the
target's own detector settings (``Target.detector``), which a separate node would have to be
told to match. The ``keypoints`` node stays a kind of its own, for viewers and other consumers.

Options: ``filter`` smooths each target's pose with the One Euro filter
(``services.estimation.pose_filter``, its options ``filter_*``; the covariance stays the
measurement's), ``align`` refines it by direct alignment (ECC), ``min_inliers`` / ``max_rms_px``
gate recognition (``RecognitionOptions``, under their own names), ``track_min_points`` /
``track_max_rms_px`` gate tracking (``TrackingOptions``, ``track_*``), ``anchor_every`` sets how often
followed points are measured afresh against the target. Frames are latest-wins (``depth``).
A frame whose stamp is not after the previous one (a source started over) starts every target
afresh.

Each target's description (``ImageTargets`` on ``<camera>/targets``: its size and its image's corners
in ``target/<name>``) is answered on that key from the start and published once, with the first frame's
header, before that frame's poses, so a recorder or viewer of the run draws the targets' outlines where
the poses place them; one that comes later asks for it (``protocol.keys.Keys.latched``). The targets are
those the node starts with, for the whole run.

``overlay``: every frame, as bgr8, on ``<camera>/overlay`` with each posed target's outline
and axes drawn (``services.estimation.overlay``), its frame id ``<frame's frame_id>/overlay``
(as the marker node's); while nothing subscribes to the key, no frame is drawn.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Annotated, Any

import cv2
import numpy as np
from pydantic import BeforeValidator, Field

from protocol.keys import KeyName
from protocol.message import Header
from protocol.poses import Pose
from protocol.sensors import Image
from protocol.targets import ImageTarget, ImageTargets
from protocol.tracking_state import TrackingState
from services.bus.pubsub import Role
from services.calibration.camera_info import read_camera_info
from services.calibration.fixed import FixedCalibration, check_own_calibration
from services.convert import CameraModels, pose_message
from services.estimation.markers.node import PosePublishers
from services.estimation.overlay import OverlayTarget, draw_overlay, to_bgr8
from services.estimation.pose_filter import OneEuroOptions, OneEuroPoseFilter
from services.estimation.targets.library import TargetLibrary
from services.estimation.targets.recognition import RecognitionOptions, RecognitionStatus
from services.estimation.targets.target import Target
from services.estimation.targets.tracking import TargetPose, TargetTracker, TrackingOptions, track_targets
from services.runtime.frame_calibration import FrameCalibration
from services.runtime.kind import NodeKind
from services.runtime.node import Node, NodeError
from services.runtime.params import Flat, NodeParams


def _as_tuple(value: Any) -> Any:
    return (value,) if isinstance(value, str) else value


class Params(NodeParams):
    """Which camera and targets, where the targets and calibration come from, and how poses are made."""

    camera: KeyName = "cam0"
    target: Annotated[tuple[str, ...], BeforeValidator(_as_tuple)] = Field(
        default=(), min_length=1, description="target names in the library; repeat for several")
    targets: Path | None = Field(default=None, description="target library folder; default "
                                                           "$XDG_DATA_HOME/artrack/targets")
    calib: Path | None = Field(default=None, description="ROS camera_info YAML; default: the camera's CameraInfo")
    recognition: Annotated[RecognitionOptions, Flat(names={
        "method": "usac_method", "measure_window_px": "refine_window_px", "measure_levels": "refine_levels",
        "measure_forward_backward_px": "refine_forward_backward_px"}, label="recognition")] = RecognitionOptions()
    tracking: Annotated[TrackingOptions, Flat("track_", names={"anchor_every": "anchor_every", "align": "align"},
                                              label="tracking")] = TrackingOptions()
    filter: bool = Field(default=False, description="smooth each pose with the One Euro filter")
    smoothing: Annotated[OneEuroOptions, Flat("filter_", label="filter")] = OneEuroOptions()
    depth: int = Field(default=2, ge=1, le=1000, description="frames queued while busy (one waits, more are "
                                                             "dropped)")
    overlay: bool = Field(default=False, description="publish the frames with each posed target's outline and "
                                                     "axes drawn")


def load_targets(params: Params) -> list[Target]:
    """The targets ``params`` name, in order; ValueError (one line) for a name not in the library, a damaged
    file, or two targets of one name."""
    library = TargetLibrary(params.targets)
    loaded = [library.load(name) for name in params.target]
    _check_unique([target.name for target in loaded])
    return loaded


def _check_unique(names: Sequence[str]) -> None:
    twice = sorted({name for name in names if names.count(name) > 1})
    if twice:
        raise ValueError(f"target {twice[0]!r} named twice: each target is tracked once per camera")


def _check(params: Params) -> None:
    """What ``load_targets`` would refuse, without reading a target: library names must exist; the calibration
    file must read."""
    library = TargetLibrary(params.targets)
    names = [library.existing(name).stem for name in params.target]
    _check_unique(names)
    if params.calib is not None:
        read_camera_info(params.calib)


def make_trackers(params: Params, targets: Sequence[Target]) -> list[TargetTracker]:
    """One tracker per target with the options of ``params``."""
    return [TargetTracker(target, params.tracking, params.recognition) for target in targets]


def target_frame(name: str) -> str:
    """The frame of the target ``name``: the child frame of its poses."""
    return f"target/{name}"


def as_pose(header: Header, found: TargetPose) -> Pose:
    """``found`` in the frame with ``header`` as the message that carries it (``target/<name>``); a covariance
    that is not finite throughout, or an RMS that is not finite, is left out."""
    child = target_frame(found.target)
    if found.T_camera_target is None:
        return Pose(header=header, child_frame_id=child, state=TrackingState.LOST, reason=found.reason)
    covariance = found.covariance
    if covariance is not None and not np.isfinite(covariance).all():
        covariance = None
    rms = float(found.rms_px)
    return pose_message(header, child, found.T_camera_target, state=found.state,
                        rms_px=rms if math.isfinite(rms) else None, inliers=found.inliers, covariance=covariance)


def described(header: Header, targets: Sequence[Target]) -> ImageTargets:
    """``targets`` as the message that describes them to the camera's consumers (``header.frame_id``: the camera's
    frame): each one's name, frame, printed size (m) and image corners in its frame (``Target.corners``)."""
    return ImageTargets(header=header, targets=tuple(
        ImageTarget(name=target.name, frame_id=target_frame(target.name), width_m=target.width_m,
                    height_m=target.height_m, corners=tuple(tuple(corner) for corner in target.corners().tolist()))
        for target in targets))


class _Descriptions:
    """The node's targets on ``<camera>/targets``: answered from the start, published once before the first poses."""

    def __init__(self, node: Node, camera: str, targets: Sequence[Target]):
        key = node.keys.targets(camera)
        self._targets = targets
        self._out = node.publisher(key, ImageTargets)
        self._message = described(Header(stamp_ns=time.time_ns(), frame_id=camera), targets)
        self._published = False
        node.answer(key, lambda: self._message)

    def publish(self, header: Header) -> None:
        """Publish the descriptions with ``header`` (a frame's), the first time only."""
        if self._published:
            return
        self._message = described(header, self._targets)
        self._out.put(self._message)
        self._published = True


class _Frames:
    """The trackers and filters of one camera, fed frame after frame (stamps increasing)."""

    def __init__(self, trackers: list[TargetTracker], smoothing: OneEuroOptions | None):
        self.trackers = trackers
        self.filters = {} if smoothing is None else {t.target.name: OneEuroPoseFilter(smoothing) for t in trackers}
        self._last_stamp: int | None = None

    def track(self, image: np.ndarray, K: np.ndarray, dist: np.ndarray | None, stamp_ns: int) -> list[TargetPose]:
        """Each target's pose in ``image`` (ValueError, cv2.error for a frame the trackers cannot read)."""
        if self._last_stamp is not None and stamp_ns <= self._last_stamp:
            for tracker in self.trackers:
                tracker.reset()
            for smoother in self.filters.values():
                smoother.reset()
        self._last_stamp = stamp_ns
        found = track_targets(self.trackers, image, K, dist, stamp_ns)
        return [self._smoothed(pose, stamp_ns) for pose in found]

    def _smoothed(self, pose: TargetPose, stamp_ns: int) -> TargetPose:
        smoother = self.filters.get(pose.target)
        if smoother is None:
            return pose
        if pose.T_camera_target is None:
            smoother.reset()
            return pose
        return dataclasses.replace(pose, T_camera_target=smoother(stamp_ns, pose.T_camera_target))

    def lost(self, reason: str) -> list[TargetPose]:
        """A ``lost`` pose of every target, for ``reason``; the next frame starts every target afresh."""
        for tracker in self.trackers:
            tracker.reset()
        return [TargetPose(TrackingState.LOST, tracker.target.name, reason) for tracker in self.trackers]


class _Overlay:
    """Publishes each frame with the outline and axes of every target posed in it."""

    def __init__(self, node: Node, camera: str, targets: Sequence[Target]):
        self._camera = camera
        self._out = node.publisher(node.keys.overlay(camera), Image, Role.FRAME)
        self._outlines = {t.name: (t.width_m, t.height_m) for t in targets}

    def put(self, image: Image, K: np.ndarray | None, dist: np.ndarray | None, found: list[TargetPose]) -> None:
        """Draw and publish ``image`` with ``found``'s posed targets; nothing while no one subscribes to the overlay."""
        if not self._out.matched():
            return
        drawn = [OverlayTarget(pose.T_camera_target, 0.5 * min(self._outlines[pose.target]), pose.target,
                               self._outlines[pose.target]) for pose in found if pose.T_camera_target is not None]
        picture = draw_overlay(image.data, K, dist, drawn) if K is not None and drawn else to_bgr8(image.data)
        header = image.header.model_copy(update={"frame_id": f"{image.header.frame_id or self._camera}/overlay"})
        self._out.put(Image(header=header, encoding="bgr8", data=picture))


def run(node: Node, params: Params) -> None:
    try:
        targets = load_targets(params)
        fixed = FixedCalibration.read(params.calib) if params.calib else None
        frames_of = _Frames(make_trackers(params, targets), params.smoothing if params.filter else None)
    except ValueError as exc:
        raise NodeError(str(exc)) from exc
    node.log.info("tracking %s on %s", ", ".join(t.name for t in targets), params.camera)
    keys = node.keys
    calibration = FrameCalibration.of_camera(node, params.camera, CameraModels(), fixed)
    poses = PosePublishers(node, params.camera)
    descriptions = _Descriptions(node, params.camera, targets)
    overlay = _Overlay(node, params.camera, targets) if params.overlay else None
    frames = node.inbox(keys.image(params.camera), Image, Role.FRAME, depth=params.depth)
    for image in node.inputs(frames):
        calibration.fit_frame(node, image)
        camera = calibration.current()
        K, dist = (camera.K, camera.dist) if camera is not None else (None, None)
        if K is None:
            found = frames_of.lost(TrackingState.NO_CALIBRATION.value)
            node.report("no_calibration", f"no CameraInfo for {params.camera} and no calib file: no poses",
                        keys.camera_info(params.camera))
        else:
            try:
                found = frames_of.track(image.data, K, dist, image.header.stamp_ns)
            except (ValueError, cv2.error) as exc:
                found = frames_of.lost("unusable_frame")
                node.report("unusable_frame", f"frame {image.header.seq}: {exc}", keys.image(params.camera))
        descriptions.publish(image.header.model_copy(update={"frame_id": image.header.frame_id or params.camera}))
        poses.publish([as_pose(image.header, pose) for pose in found])
        if any(pose.reason == RecognitionStatus.NO_FEATURES for pose in found):
            node.report(RecognitionStatus.NO_FEATURES.value, f"frame {image.header.seq}: no keypoints to recognise "
                        "a target by", keys.image(params.camera))
        if overlay is not None:
            overlay.put(image, K, dist, found)
        calibration.refresh()


def _outputs(params: Params) -> tuple[str, ...]:
    return (f"pose/{params.camera}/target/**", f"{params.camera}/targets",
            *((f"{params.camera}/overlay",) if params.overlay else ()))


KIND = NodeKind(name="features", summary="image targets' poses from a camera's frames: recognised by keypoints, "
                "then followed by Lucas-Kanade", params=Params, run=run,
                inputs=("{camera}/image", "{camera}/camera_info"), outputs=_outputs, check=_check,
                check_frames=check_own_calibration)
