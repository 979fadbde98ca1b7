"""SLAM node: one camera's frames -> the camera's pose in a map built as it goes (``services.slam.system``).

Inputs: the camera's ``image`` key (up to ``depth`` frames, 10, waiting while one is processed, the oldest
dropped past that: a stall of the tracker, waiting for the mapper or bridging a gap, costs latency rather
than frames, and a camera moving forward lost after three frames dropped has no map to come back to) and its
``camera_info`` key (the newest CameraInfo, taken in between frames: ``services.runtime.frame_calibration``; a
``calib`` file given here wins, scaled to the frames when only their size differs:
``services.calibration.fixed``). Frames may be ``mono8``, ``mono16``, ``bgr8`` or ``bgra8``; SLAM is given
their grey levels.

Outputs, each with the header of the frame it came from (``frame_id`` the map frame, ``map_frame``):

* ``pose/slam/<camera>``, every frame: a ``Pose`` ``T_<map_frame>_<camera>`` (child frame the frame's
  ``frame_id``, else the camera's name), state ``initialising`` (no map yet), ``tracking`` or ``lost``,
  ``reason`` when not tracking (the system's: ``low_parallax``, ``too_few_matches``, ...; the node's own:
  ``no_calibration``, ``unusable_frame``; ``calibration_suspect`` on a tracked frame once the camera matrix
  failed the system's check), quality ``inliers`` (map points tracked in the frame) and
  ``reprojection_rms_px``. The map frame is the first keyframe's camera frame, and its scale is arbitrary
  (monocular): compare with ground truth after a similarity alignment (``artrack eval --align sim3``).
* ``<camera>/keyframes``: a ``Keyframes`` message (ids, stamps, (K, 4, 4) ``T_map_camera``), whenever the
  map changed and the keyframes with it (one added, or moved by the map's optimisation).
* ``<camera>/trajectory``: a ``Trajectory`` (stamps, sequence numbers, (N, 4, 4) ``T_map_camera``) when a map
  ends (the node stops, or a new map replaces it), its mapping finished first: every frame it tracked through
  its reference keyframe's final pose, what SLAM benchmarks score (the ``pose/slam/<camera>`` poses are the
  online ones, as tracked).
* ``<camera>/map``: the map points as a ``PointCloud`` (ids the map's point ids, no colours), at most
  ``map_points`` of them (evenly spread over the ids when the map holds more), sent when the map changed
  and at most every ``map_every`` frames, and once more when the node stops.
* ``<camera>/timings``: a ``StageTimings`` per frame, the system's time per stage in milliseconds (the
  node's own processing p50/p99 stays in its stats).
* ``pose/slam/<camera>/anchored``, with ``anchor_marker`` set (off by default): every frame the system
  processed, the camera in the anchor marker's frame, in metres: ``T_marker/<id>_<camera>`` (header
  ``frame_id`` ``marker/<id>``). The node detects and poses that marker in each tracked frame itself
  (``dictionary``, ``marker_length`` and the rest of the marker detector's options; the marker tracker's
  detector and estimator) and fits the map's scale and pose to its sightings (``services.slam.anchor``, with
  the ``anchor_*`` settings); state ``tracking`` once anchored, before
  that ``initialising`` with the anchor's status as ``reason`` (``too_few_frames``, ``short_baseline``,
  ...), ``lost`` with the system's reason when the frame has no pose. A new map starts a new anchor.

The SLAM system's settings (``services.slam.settings``) are the node's too, under their own names
(``max_keypoints``, ``min_tracked``, ...).

With the mapping process (``mapping``, the default) the node spawns that process when it starts, so
that its imports are done before the first frame (``mapping_process.prepare``).

Lossless runs (a finite source whose every frame reaches the node in order, ``node.flow.lossless``): each
new keyframe is mapped before the next frame is tracked (``SlamSystem``'s ``wait_for_mapping``; the source
waits for the node meanwhile), so the poses are those of inline mapping, the same on a loaded machine as on
an idle one. In a real-time run a busy mapper means no keyframe yet; the tracker waits for it (frames that
come meanwhile queue, up to ``depth``) only after a keyframe made on a nearly lost frame, which would
otherwise leave the next frames no map to track against.

Map files (``services.slam.map.file``): with ``map`` every new system starts from that file's map
(relocalising in it first), with ``localisation_only`` too that map stays fixed; with ``save_map`` the last
system's map is written when the node stops (not when it holds no keyframe; a file that cannot be written is
one error line). A map file that is missing, not a map file or of another version is refused before the node
starts (``check``); one made for another camera shows only once the calibration is known: one error line,
then every frame of that calibration gets a ``lost`` pose ``map_refused`` (counted and reported like the
frames below) while the node goes on.

Frames the node cannot use are counted among its skipped inputs and reported on its errors key, and get a
``lost`` pose: ``no_calibration`` before the camera has one, ``unusable_frame`` for a frame whose size is
not the calibration's or that the system refuses. Payloads that do not decode are counted by the inbox.
A frame stamped at most ``STEP_BACK_S`` (1 s) before the newest one so far (late, or the same stamp twice) is
out of order: skipped by the system, it gets a ``lost`` pose ``out_of_order`` and is counted and reported like
the frames above. A frame stamped further back (a source started over), or a new calibration, starts a new map
(from ``map`` again when given); the system is closed when the node stops.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal

import cv2
import numpy as np
from pydantic import Field

from protocol.keys import KeyName
from protocol.maps import Keyframes, PointCloud, Trajectory
from protocol.message import Header
from protocol.poses import Pose, PoseQuality
from protocol.sensors import Image
from protocol.spatial import Transform
from protocol.system import StageTimings
from protocol.tracking_state import TrackingState
from services.bus.pubsub import Role
from services.calibration.camera_info import read_camera_info
from services.calibration.fixed import FixedCalibration, check_own_calibration
from services.convert import camera_model, transform_from_matrix
from services.detection.grey import as_grey
from services.detection.markers.settings import DetectorSettings
from services.estimation.markers.pose import MarkerPoseEstimator
from services.geometry.camera import CameraModel
from services.runtime.frame_calibration import FrameCalibration
from services.runtime.kind import NodeKind
from services.runtime.node import Node, NodeError
from services.runtime.params import Flat, NodeParams
from services.slam import mapping_process
from services.slam.anchor import AnchorSettings, MarkerAnchor, MarkerSighting
from services.slam.map.file import MapFileError, read_header
from services.slam.settings import SlamSettings
from services.slam.system import STEP_BACK_S, FrameResult, SlamSystem


class Params(NodeParams):
    """Which camera, where its calibration comes from, what of the map is published how often, the anchor
    marker and the SLAM system's settings."""

    camera: KeyName = "cam0"
    calib: Path | None = Field(default=None, description="ROS camera_info YAML; default: the camera's CameraInfo")
    map_frame: KeyName = Field(default="map", description="frame id of the map (the first keyframe's camera "
                                                          "frame, arbitrary scale)")
    map_points: int = Field(default=20_000, ge=1, description="most map points in one published map (evenly "
                                                              "spread over the map's when it holds more)")
    map_every: int = Field(default=10, ge=1, description="publish the map at most every this many frames (when "
                                                         "it changed)")
    mapping: Literal["process", "thread", "inline"] = Field(
        default="process", description="where local mapping runs: a process of its own, a thread, or inline (in "
                                       "the frame loop: each frame waits for the mapping it starts)")
    depth: int = Field(default=10, ge=1, le=1000, description="frames queued while busy (the oldest dropped "
                                                              "past that)")
    map: Path | None = Field(default=None, description="map file of an earlier run (--save-map) to start from: "
                                                       "relocalise in it, then track it")
    localisation_only: bool = Field(default=False, description="keep the loaded map fixed: no new keyframes or "
                                                               "points (needs --map)")
    save_map: Path | None = Field(default=None, description="write the map to this file when the node stops")
    anchor_marker: int | None = Field(default=None, ge=0, description="id of a marker of known side whose "
                                      "sightings give the map metres and the marker's frame "
                                      "(pose/slam/<camera>/anchored); default: off")
    marker: Annotated[DetectorSettings, Flat(label="anchor marker")] = DetectorSettings()
    anchor: Annotated[AnchorSettings, Flat("anchor_", label="anchor")] = AnchorSettings()
    slam: Annotated[SlamSettings, Flat()] = SlamSettings()


def _check(params: Params) -> None:
    """What the node would refuse at its start (ValueError, one line): a calibration file that does not read,
    a map file that is missing, not a map file or of another version, localisation without a map, a map
    to save into a folder that does not exist, an anchor marker without its side or of an unknown dictionary."""
    if params.calib is not None:
        read_camera_info(params.calib)
    if params.localisation_only and params.map is None:
        raise ValueError("localisation_only needs a map to localise in (map, --map)")
    if params.map is not None:
        read_header(params.map)
    if params.save_map is not None and params.save_map.is_dir():
        raise ValueError(f"cannot save the map to {params.save_map}: a folder")
    if params.save_map is not None and not params.save_map.parent.is_dir():
        raise ValueError(f"cannot save the map to {params.save_map}: no folder {params.save_map.parent}")
    if params.anchor_marker is not None:
        _Anchoring(params)


class _Anchoring:
    """The anchor marker posed in each tracked frame, and the map -> marker anchor its sightings give."""

    def __init__(self, params: Params):
        if params.marker.marker_length is None:
            raise ValueError("anchor_marker needs the marker's side: marker_length (metres) is not set")
        self.target = f"marker/{params.anchor_marker}"
        self.detector = params.marker.detector()
        self.estimator = MarkerPoseEstimator()
        self.anchor = MarkerAnchor(params.anchor)

    def to_marker(self, camera: CameraModel, grey: np.ndarray, T_map_camera: np.ndarray) -> np.ndarray | None:
        """The frame's ``T_marker_camera`` (4, 4), metres, once anchored (after adding this frame's sighting)."""
        found = self.detector.detect(grey, camera.K, camera.dist)
        estimate = self.estimator.estimate(found.ids, found.corners, found.side_m, camera.K, camera.dist)
        for pose in estimate.poses:
            if pose.target == self.target:
                self.anchor.add(T_map_camera, MarkerSighting(pose.T, pose.rms_px, pose.ambiguous, pose.covariance))
        return None if self.anchor.anchor is None else self.anchor.anchor.to_marker(T_map_camera)


def decimated(ids: np.ndarray, points: np.ndarray, most: int) -> tuple[np.ndarray, np.ndarray]:
    """``(ids, points)`` ((N,) and (N, 3)) cut to at most ``most`` rows, evenly spaced over the rows."""
    if len(ids) <= most:
        return ids, points
    keep = np.linspace(0, len(ids) - 1, most).round().astype(np.int64)
    return ids[keep], points[keep]


def as_pose(header: Header, child: str, result: FrameResult) -> Pose:
    """The frame's ``Pose`` message from the system's ``result``."""
    quality = PoseQuality(inliers=max(result.tracked, 0), reprojection_rms_px=(
        float(result.reprojection_rms_px) if np.isfinite(result.reprojection_rms_px) else None))
    T = result.T_world_camera
    return Pose(header=header, child_frame_id=child, state=result.state, reason=result.reason,
                quality=quality, transform=Transform() if T is None else transform_from_matrix(T))


def _same_camera(a: CameraModel, b: CameraModel) -> bool:
    return (a.width, a.height) == (b.width, b.height) and np.array_equal(a.K, b.K) and np.array_equal(a.dist, b.dist)


class _CameraSlam:
    """One camera's SLAM system and what of its map was published last."""

    def __init__(self, node: Node, params: Params):
        self._node = node
        self._params = params
        keys = node.keys
        self._poses = node.publisher(keys.slam_pose(params.camera), Pose, Role.RESULT)
        self._timings = node.publisher(keys.timings(params.camera), StageTimings, Role.RESULT)
        self._keyframes = node.publisher(keys.keyframes(params.camera), Keyframes, Role.RESULT)
        self._trajectory = node.publisher(keys.trajectory(params.camera), Trajectory, Role.RESULT)
        self._cloud = node.publisher(keys.camera_map(params.camera), PointCloud, Role.RESULT)
        self._anchored = (None if params.anchor_marker is None else
                          node.publisher(keys.pose(f"slam/{params.camera}/anchored"), Pose, Role.RESULT))
        self.system: SlamSystem | None = None
        self._camera: CameraModel | None = None
        self._last_stamp: int | None = None
        self._refused: tuple[CameraModel, MapFileError] | None = None
        self._start_over()

    def _start_over(self) -> None:
        self._seqs: dict[int, int] = {}
        """Stamp -> sequence number of each frame the system took."""
        self._last: tuple[Header, str] | None = None
        """The map-frame header and child frame of the last frame published."""
        self._keyframe_revision: int | None = None
        self._sent_keyframes: tuple[np.ndarray, np.ndarray] | None = None
        self._map_revision: int | None = None
        self._since_map = self._params.map_every
        self._anchoring = None if self._params.anchor_marker is None else _Anchoring(self._params)

    def system_for(self, camera: CameraModel, stamp_ns: int) -> SlamSystem:
        """The system for a frame of ``camera`` stamped ``stamp_ns``: a new one (a new map, or ``map``'s) at
        the first frame, after a new calibration and when the stamps start over (step back by more than
        ``STEP_BACK_S``; a frame less far back is the system's to skip). ``MapFileError`` when
        ``map`` does not fit ``camera`` (once logged as an error; raised again for every frame of it)."""
        if self._refused is not None and _same_camera(camera, self._refused[0]):
            raise self._refused[1]
        last = self._last_stamp
        restarted = last is not None and last - stamp_ns > STEP_BACK_S * 1e9
        recalibrated = self._camera is not None and not _same_camera(camera, self._camera)
        self._last_stamp = stamp_ns if last is None or restarted else max(last, stamp_ns)
        if self.system is None or restarted or recalibrated:
            if self.system is not None:
                self._node.log.warning("a new map for %s: %s", self._params.camera,
                                       "the frames started over" if restarted else "the calibration changed")
                self.close()
            self._camera = camera
            self._start_over()
            self.system = self._new_system(camera)
        return self.system

    def _new_system(self, camera: CameraModel) -> SlamSystem:
        params = self._params
        try:
            system = SlamSystem(camera, params.slam, mapping=params.mapping, map_path=params.map,
                                localisation_only=params.localisation_only, wait_for_mapping=self._node.flow.lossless)
        except MapFileError as error:
            self._node.log.error("%s: no poses for %s with this calibration", error, params.camera)
            self._refused = (camera, error)
            raise
        self._refused = None
        if params.map is not None:
            self._node.log.info("%s: %d keyframes loaded from %s%s", params.camera, len(system.map.keyframes),
                                params.map, " (localisation only)" if params.localisation_only else "")
        return system

    def put_pose(self, pose: Pose) -> None:
        self._poses.put(pose)

    def publish(self, header: Header, child: str, result: FrameResult) -> None:
        """The frame's pose, stage times, and what of the map changed (see the module docstring)."""
        map_header = header.model_copy(update={"frame_id": self._params.map_frame})
        self._poses.put(as_pose(map_header, child, result))
        self._seqs[header.stamp_ns] = header.seq
        self._last = map_header, child
        stages = {stage: float(ms) for stage, ms in result.timings_ms.items() if np.isfinite(ms) and ms >= 0}
        self._timings.put(StageTimings(header=header, stages_ms=stages))
        self._since_map += 1
        self.publish_map(map_header, child, final=False)

    def publish_anchored(self, header: Header, child: str, camera: CameraModel, grey: np.ndarray,
                         result: FrameResult) -> None:
        """With an anchor marker: the frame's pose in the marker's frame, or why there is none."""
        if self._anchoring is None or self._anchored is None:
            return
        marker_header = header.model_copy(update={"frame_id": self._anchoring.target})
        T = None if result.T_world_camera is None else self._anchoring.to_marker(camera, grey, result.T_world_camera)
        if T is None:
            waiting = result.state is TrackingState.TRACKING
            self._anchored.put(Pose(header=marker_header, child_frame_id=child,
                                    state=TrackingState.INITIALISING if waiting else result.state,
                                    reason=self._anchoring.anchor.status.value if waiting else result.reason))
            return
        pose = as_pose(marker_header, child, result)
        self._anchored.put(pose.model_copy(update={"transform": transform_from_matrix(T)}))

    def publish_map(self, header: Header, child: str, *, final: bool) -> None:
        """Keyframes when they changed; points when the map changed and ``map_every`` frames went by (or
        ``final``)."""
        system = self.system
        if system is None:
            return
        revision = system.map_revision
        if revision != self._keyframe_revision:
            self._keyframe_revision = revision
            self._put_keyframes(header, child, system.keyframe_poses())
        if revision != self._map_revision and (final or self._since_map >= self._params.map_every):
            self._map_revision = revision
            self._since_map = 0
            ids, points = system.map_points()
            ids, points = decimated(ids, points, self._params.map_points)
            self._cloud.put(PointCloud(header=header, points=np.asarray(points, np.float32),
                                       ids=np.asarray(ids, np.int64), colors=np.zeros((0, 3), np.uint8)))

    def _put_keyframes(self, header: Header, child: str, keyframes: list[tuple[int, int, np.ndarray]]) -> None:
        ids = np.array([k for k, _, _ in keyframes], np.int64)
        poses = np.array([T for _, _, T in keyframes], np.float64).reshape(-1, 4, 4)
        sent = self._sent_keyframes
        if sent is not None and np.array_equal(sent[0], ids) and np.array_equal(sent[1], poses):
            return
        self._sent_keyframes = (ids, poses)
        stamps = np.array([stamp for _, stamp, _ in keyframes], np.int64)
        self._keyframes.put(Keyframes(header=header, child_frame_id=child, ids=ids, stamps_ns=stamps, poses=poses))

    def close(self) -> None:
        """End the system's map: its mapping finished, its final keyframes, points and trajectory published."""
        if self.system is not None:
            self.system.close()
            if self._last is not None:
                self.publish_map(*self._last, final=True)
                self._put_trajectory(*self._last, self.system.trajectory())
            self.system = None

    def _put_trajectory(self, header: Header, child: str, trajectory: list[tuple[int, np.ndarray]]) -> None:
        stamps = np.array([stamp for stamp, _ in trajectory], np.int64)
        self._trajectory.put(Trajectory(header=header, child_frame_id=child, stamps_ns=stamps,
                                        seqs=np.array([self._seqs.get(int(stamp), -1) for stamp in stamps], np.int64),
                                        poses=np.array([T for _, T in trajectory], np.float64).reshape(-1, 4, 4)))

    def stop(self) -> None:
        """Close the system, then save its map to ``save_map`` when given: a map without keyframes is not
        saved (a warning), a file that cannot be written is one error line."""
        system, path = self.system, self._params.save_map
        self.close()
        if path is None:
            return
        if system is None or not system.map.keyframes:
            self._node.log.warning("no map saved to %s: no map of %s with keyframes", path, self._params.camera)
            return
        try:
            system.save_map(path)
        except MapFileError as error:
            self._node.log.error("%s", error)
            return
        self._node.log.info("map of %s saved to %s: %d keyframes, %d points", self._params.camera, path,
                            len(system.map.keyframes), len(system.map.points))


def run(node: Node, params: Params) -> None:
    try:
        _check(params)
        fixed = FixedCalibration.read(params.calib) if params.calib else None
    except ValueError as exc:
        raise NodeError(str(exc)) from exc
    keys = node.keys
    if params.mapping == "process" and not params.localisation_only:
        mapping_process.prepare()  # its imports run before the first frame, which then need not wait for them
    calibration = FrameCalibration.of_camera(node, params.camera, camera_model, fixed)
    slam = _CameraSlam(node, params)
    frames = node.inbox(keys.image(params.camera), Image, Role.FRAME, depth=params.depth)
    try:
        for image in node.inputs(frames):
            calibration.fit_frame(node, image)
            _track(node, params, slam, calibration.current(), image, image.header.frame_id or params.camera)
            calibration.refresh()
    finally:
        slam.stop()


def _track(node: Node, params: Params, slam: _CameraSlam, camera: CameraModel | None, image: Image, child: str) -> None:
    """One frame through the system, or the ``lost`` pose that says why it could not be."""
    header = image.header
    lost = header.model_copy(update={"frame_id": params.map_frame})
    where = node.keys.image(params.camera)
    if camera is None:
        slam.put_pose(Pose(header=lost, child_frame_id=child, state=TrackingState.LOST, reason="no_calibration"))
        node.report("no_calibration", f"no CameraInfo for {params.camera} and no calib file: no poses",
                    node.keys.camera_info(params.camera))
        return
    height, width = image.data.shape[:2]
    try:
        if (width, height) != (camera.width, camera.height):
            raise ValueError(f"a {width}x{height} frame, calibrated for {camera.width}x{camera.height}")
        grey = as_grey(image.data)
        result = slam.system_for(camera, header.stamp_ns).process(header.stamp_ns, grey)
    except MapFileError as exc:
        slam.put_pose(Pose(header=lost, child_frame_id=child, state=TrackingState.LOST, reason="map_refused"))
        node.report("map_refused", f"frame {header.seq}: {exc}", node.keys.camera_info(params.camera))
        return
    except (ValueError, cv2.error) as exc:
        slam.put_pose(Pose(header=lost, child_frame_id=child, state=TrackingState.LOST, reason="unusable_frame"))
        node.report("unusable_frame", f"frame {header.seq}: {exc}", where)
        return
    if result.reason == "out_of_order":
        node.report("out_of_order", f"frame {header.seq}: stamped {header.stamp_ns} ns, not after an earlier frame",
                    where)
    slam.publish(header, child, result)
    slam.publish_anchored(header, child, camera, grey, result)


def _outputs(params: Params) -> tuple[str, ...]:
    anchored = () if params.anchor_marker is None else (f"pose/slam/{params.camera}/anchored",)
    return (f"pose/slam/{params.camera}", *(f"{params.camera}/{stream}" for stream in ("keyframes", "map",
                                                                                          "timings")), *anchored)


KIND = NodeKind(name="slam", summary="monocular SLAM: the camera's pose in a map of keyframes and points built "
                "from its frames", params=Params, run=run, inputs=("{camera}/image", "{camera}/camera_info"),
                outputs=_outputs, check=_check, check_frames=check_own_calibration)
