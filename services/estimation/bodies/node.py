"""Rigid bodies node: the blobs of every camera of a calibrated rig -> 3D points -> ``T_world_body`` poses.

Inputs: ``<camera>/blobs`` of each of ``cameras`` (``protocol.detections.Blobs``, one blobs node per
camera), joined by ``header.seq``: only the blobs of one instant are ever triangulated together;
a camera's blobs that find no partners are counted as unjoined in the node's statistics
(``NodeStats.synced``), never used. In a lossless run every set is taken in order; in real time a node that
falls behind (a busy machine, more cameras than it can follow) lets the newest ``backlog`` complete sets wait
and counts the older ones dropped (``Node.synced``'s ``backlog``), so the poses never queue behind it for
more than that. The blobs come as results: a frame a blobs node dropped is counted there, not again here.

The rig (world = the rig frame) is the ``rig_file`` (``services.calibration.rig``), else each camera's newest
``<camera>/camera_info``, whose ``T_rig_camera`` places it on the rig (a synthetic ``ir_rig`` scene publishes
its cameras so), taken in between sets, once a set's results are out.
The bodies are the ``bodies`` file (``services.estimation.bodies.file``; ``artrack run`` gives a
synthetic ``ir_rig`` source's own); what ``check_bodies`` finds doubtful about them is logged at
start, one line each. Without a file the node looks for no body: every point is published
unlabelled (body -1), from which ``artrack bodies define`` makes bodies, and no pose.

Per joined set the blobs without flags (``flagged`` uses the flagged ones too) become 3D points and the
bodies are found among them and each fitted (``BodiesPerSet``). With ``predict`` (the default) the bodies are
followed from set to set (``services.estimation.bodies.tracking.BodyTracker``): each body's constant-velocity
motion, from its last two fits and their stamps, predicts its pose at the set's stamp, and the set goes
through ``services.estimation.bodies.labelled.track_blobs``: the predicted spheres of every body projected
into every camera label the blobs within ``predict_gate_px`` of them (a blob near two predicted spheres is
doubtful and labels none), each sphere labelled in two cameras or more is triangulated over its views, and
each body fitted to its labelled points without a search; the blobs left (the first sets, a body lost or
new, strays) go through the full path below, and the bodies not fitted are looked for among its points,
within ``predict_gate`` of their prediction first. Without ``predict`` (``predict=false``), every set takes
the full path alone: all blobs put in correspondence and triangulated
(``services.estimation.bodies.correspondence``), the bodies matched among the points by their distances
(``services.estimation.bodies.rigid``). Outputs, with the header of the set's frames and ``frame_id``
``world``:

* ``points``: ``Points3D``, every point with its residual, views, covariance and body (-1: none); the
  covariances are for centroid noise of ``sigma_px``, by default (``auto``) the running estimate of
  ``services.estimation.bodies.centroid_noise.CentroidNoise`` from the points' reprojection residuals;
  built and published only while something subscribes to it (a recorder, a viewer, an app), as it costs
  about a tenth of a set's work and the poses do not need it;
* ``pose/body/<name>``: ``Pose`` ``T_world_body`` (child ``body/<name>``) per body found, state
  ``tracking``, with the spheres used (``quality.inliers``), the fit's residual RMS
  (``quality.residual_rms_m``) and its 6x6 covariance (``Pose``'s convention: perturbation
  (tx, ty, tz, rx, ry, rz) in the body frame); a body found in the previous set and not in this
  one gets one ``lost`` pose (identity transform).

With ``predict``, a body found in the previous set and missing from this one gets one pose with state
``predicted`` (the predicted transform, covariance grown by the extrapolation, no inliers), then ``lost``
if still missing at the next set. A motion is forgotten after ``predict_gap_s`` without a fit.

The compiled kernels are loaded (``kernels.warm``) before the node takes its first set.
Until every camera has a calibration, sets are counted as skipped (``no_calibration``). A rig file is used
as it is: one whose camera was calibrated at another size than that camera's frames is refused before
start wherever the source tells the frame size (``check_frames``).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import numpy as np
from pydantic import Field, field_validator

from protocol.detections import BLOB_SPLIT, Blobs
from protocol.keys import KeyName
from protocol.message import Header
from protocol.mocap import Points3D
from protocol.poses import Pose
from protocol.sensors import CameraInfo
from protocol.tracking_state import TrackingState
from services.bus.pubsub import Inbox, Publisher, Role
from services.calibration.rig import Rig, read_rig
from services.convert import CameraModels, pose_message
from services.estimation.bodies import kernels
from services.estimation.bodies.centroid_noise import CentroidNoise
from services.estimation.bodies.correspondence import CorrespondenceOptions, triangulate_blobs
from services.estimation.bodies.file import check_bodies, load_bodies
from services.estimation.bodies.labelled import Found, track_blobs
from services.estimation.bodies.rigid import Matching, MatchOptions, match_bodies
from services.estimation.bodies.tracking import BodyTracker, TrackingOptions
from services.estimation.markers.tracking import TargetTracks
from services.geometry.absolute_orientation import child_frame_covariance
from services.geometry.camera import CameraModel
from services.geometry.triangulation import TriangulatedPoint
from services.runtime import compiled
from services.runtime.kind import FrameSizes, NodeKind
from services.runtime.node import Node, NodeError
from services.runtime.params import Flat, NodeParams

if TYPE_CHECKING:
    from services.estimation.motion import Prediction

WORLD = "world"
FIRST_INFO_WAIT_S = 0.5
"""The longest the first set waits for the cameras' first CameraInfo."""
INFO_DEPTH = 100


class Params(NodeParams):
    """The rig's cameras, its calibration and bodies, and the options of correspondence, matching and tracking."""

    cameras: tuple[KeyName, ...] = Field(default=("cam0", "cam1"), description="the rig's cameras, whose blobs "
                                                                               "are joined")
    rig_file: Path | None = Field(default=None, description="rig YAML (docs/rig-file.md); default: the "
                                                            "cameras' CameraInfo with their T_rig_camera")
    bodies: Path | None = Field(default=None, description="bodies YAML; default: none, every point unlabelled")
    flagged: bool = Field(default=False, description="also triangulate blobs flagged merged, occluded or clipped")
    correspondence: Annotated[CorrespondenceOptions, Flat()] = CorrespondenceOptions()
    match: Annotated[MatchOptions, Flat()] = MatchOptions()
    sync_depth: int = Field(default=8, ge=1, le=1000, description="blobs kept per camera waiting for partners")
    backlog: int = Field(default=2, ge=1, le=1000, description="in real time, complete sets of blobs that may wait "
                                                               "while the node is busy; older ones are dropped")
    predict: bool = Field(default=True, description="follow each body with a constant-velocity prediction: its "
                                                    "spheres labelled in the images first, one missing set bridged")
    tracking: Annotated[TrackingOptions, Flat("predict_", names={
        "motion_max_gap_s": "predict_gap_s", "motion_acceleration": "predict_acceleration",
        "motion_angular_acceleration": "predict_angular_acceleration"}, label="predict")] = TrackingOptions()

    @field_validator("cameras")
    @classmethod
    def _a_rig(cls, cameras: tuple[str, ...]) -> tuple[str, ...]:
        if len(cameras) < 2 or len(set(cameras)) != len(cameras):
            raise ValueError(f"triangulating needs two or more distinct cameras, got {', '.join(cameras) or 'none'}")
        return cameras


def load(params: Params) -> tuple[Rig | None, dict[str, np.ndarray]]:
    """The rig file's cameras (None without a file) and the bodies (none without a file); ValueError (one line)
    when unusable."""
    rig = None
    if params.rig_file is not None:
        rig = read_rig(params.rig_file)
        missing = [name for name in params.cameras if name not in rig.names]
        if missing:
            raise ValueError(f"{params.rig_file}: no camera {', '.join(missing)} in the rig (it has "
                             f"{', '.join(rig.names)})")
    return rig, {} if params.bodies is None else load_bodies(params.bodies)


class Calibration:
    """Each camera's model: the rig file's, or the newest CameraInfo of each camera."""

    def __init__(self, cameras: tuple[str, ...], rig: Rig | None, infos: Mapping[str, Inbox[CameraInfo]]):
        self.cameras = cameras
        self.infos = infos
        self.models: dict[str, CameraModel] = {} if rig is None else {name: rig.camera(name) for name in cameras}
        self.waited = False
        self._streams = {name: CameraModels(name) for name in cameras}

    def current(self) -> list[CameraModel] | None:
        """The cameras in ``cameras`` order, None while one has no calibration yet (the newest CameraInfo of each
        then taken in: ``refresh``, which the node otherwise does once a set's results are out)."""
        if len(self.models) < len(self.cameras):
            self.refresh()
        if len(self.models) < len(self.cameras) and not self.waited:
            self.waited = True
            for name in self.cameras:
                if name not in self.models and (received := self.infos[name].recv(FIRST_INFO_WAIT_S)) is not None:
                    self.models[name] = self._streams[name](received.message)
        if len(self.models) < len(self.cameras):
            return None
        return [self.models[name] for name in self.cameras]

    def missing(self) -> list[str]:
        return [name for name in self.cameras if name not in self.models]

    def refresh(self) -> None:
        """Take in the newest CameraInfo of each camera that arrived (none with a rig file); a camera's model
        is rebuilt only when its CameraInfo changed (a source sends it with every frame)."""
        for name, inbox in self.infos.items():
            if (newest := inbox.take_newest()) is not None:
                self.models[name] = self._streams[name](newest.message)


def pixels(blobs: Blobs, flagged: bool) -> np.ndarray:
    """(N, 2) float64 centroids of the blobs to triangulate: the unflagged ones, or with ``flagged`` all but the
    parts of split blobs."""
    return blobs.centroids[(blobs.flags & BLOB_SPLIT) == 0] if flagged else blobs.centroids[blobs.flags == 0]


def split_parts(blobs: Blobs) -> np.ndarray:
    """(P, 2, 2) float64: the two parts' centroids (px) of each split blob, the ``BLOB_SPLIT`` rows in pairs."""
    return blobs.centroids[(blobs.flags & BLOB_SPLIT) != 0].reshape(-1, 2, 2)


def point_arrays(found: list[TriangulatedPoint]) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) float64 points (world) and (N, 3, 3) float64 covariances (m^2) of ``found``."""
    return (np.array([p.point for p in found], np.float64).reshape(-1, 3),
            np.array([p.covariance for p in found], np.float64).reshape(-1, 3, 3))


class PointNoise:
    """The points' covariances under the centroid noise: ``sigma_px`` fixed (the points triangulated with it),
    or ``auto``: estimated by a ``CentroidNoise`` from each set's residuals (the points triangulated with 1 px)."""

    def __init__(self, options: CorrespondenceOptions):
        self.noise = CentroidNoise() if options.sigma_px == "auto" else None

    def arrays(self, found: list[TriangulatedPoint]) -> tuple[np.ndarray, np.ndarray]:
        """``point_arrays`` of one set's points, their covariances scaled by the estimate once it has taken
        them in."""
        points, covariances = point_arrays(found)
        if self.noise is None:
            return points, covariances
        sigma_px = self.noise.update(np.array([p.rms_px for p in found]), np.array([p.views for p in found]))
        return points, covariances * sigma_px**2


class BodiesPerSet:
    """What the node does with each joined set: its points and the bodies among them, with ``predict`` the
    bodies followed (``BodyTracker``, ``labelled.track_blobs``), else the full path alone (``triangulate_blobs``,
    then ``match_bodies``)."""

    def __init__(self, bodies: Mapping[str, np.ndarray], params: Params):
        self.bodies = dict(bodies)
        self.params = params
        self.noise = PointNoise(params.correspondence)
        self.tracker = BodyTracker(bodies, params.match, params.tracking) if params.predict else None

    def __call__(self, stamp_ns: int, cameras: list[CameraModel], blobs: list[np.ndarray],
                 parts: list[np.ndarray] | None = None) -> tuple[Found, dict[str, Prediction]]:
        """The set's ``Found`` and name -> ``Prediction`` of the bodies bridged (``find``), its fits then taken
        into the bodies' motion (``learn``). ``blobs[c]``: (N_c, 2) pixels of ``cameras[c]`` (``pixels``);
        ``parts[c]``: (P_c, 2, 2) its split blobs' parts (``split_parts``), used by the bodies followed."""
        found, predicted = self.find(stamp_ns, cameras, blobs, parts)
        self.learn(stamp_ns, found)
        return found, predicted

    def find(self, stamp_ns: int, cameras: list[CameraModel], blobs: list[np.ndarray],
             parts: list[np.ndarray] | None = None) -> tuple[Found, dict[str, Prediction]]:
        """``__call__`` but for ``learn``: what the node publishes, before it takes the fits in."""
        params = self.params
        if self.tracker is None:
            made = triangulate_blobs(cameras, blobs, params.correspondence)
            points, covariances = self.noise.arrays(made)
            matching = match_bodies(self.bodies, points, covariances, params.match) if len(made) else Matching()
            return Found(made, points, covariances, matching), {}
        forecasts = self.tracker.forecast(stamp_ns)
        found = track_blobs(cameras, blobs, self.bodies, {name: f.T_world_body for name, f in forecasts.items()},
                            self.noise.arrays, params.correspondence, params.match, params.tracking, parts)
        return found, self.tracker.bridge(found.matching, forecasts).predicted

    def learn(self, stamp_ns: int, found: Found) -> None:
        """The bodies found at ``stamp_ns`` into their motion (with ``predict``), for the next set."""
        if self.tracker is not None:
            self.tracker.learn(stamp_ns, found.matching)


def points_message(header: Header, found: list[TriangulatedPoint], names: list[str], matching: Matching,
                   covariances: np.ndarray | None = None) -> Points3D:
    """The set's points with the body each was matched to; ``covariances`` (N, 3, 3) m^2 when not the points'
    own."""
    body = np.full(len(found), -1, np.int32)
    for match in matching.bodies.values():
        body[match.indices[match.indices >= 0]] = names.index(match.name)
    points, own = point_arrays(found)
    covariances = own if covariances is None else covariances
    return Points3D(header=header, bodies=tuple(names), points=points,
                    residual_px=np.array([p.rms_px for p in found], np.float32),
                    views=np.array([p.views for p in found], np.uint8), covariances=covariances, body=body)


def body_poses(header: Header, matching: Matching) -> list[Pose]:
    """One ``tracking`` pose per body found."""
    return [pose_message(header, f"body/{name}", match.fit.T_world_body, inliers=match.spheres_used,
                         residual_rms_m=match.fit.residual_rms,
                         covariance=None if match.fit.covariance is None else
                         child_frame_covariance(match.fit.covariance, match.fit.T_world_body))
            for name, match in matching.bodies.items()]


def predicted_poses(header: Header, predicted: Mapping[str, Prediction]) -> list[Pose]:
    """One ``predicted`` pose per body bridged: the predicted transform and its grown covariance, no inliers."""
    return [pose_message(header, f"body/{name}", p.T_world_body, state=TrackingState.PREDICTED,
                         covariance=child_frame_covariance(p.covariance, p.T_world_body))
            for name, p in predicted.items()]


class PosePublishers:
    """One publisher per body, made when the body is first found; one ``lost`` pose when it goes."""

    def __init__(self, node: Node):
        self.node = node
        self.publishers: dict[str, Publisher[Pose]] = {}
        self.tracks = TargetTracks()

    def put(self, header: Header, tracking: list[Pose]) -> None:
        """Publish this set's poses (``tracking`` or ``predicted``), and one ``lost`` pose per body they lack
        that the previous set had."""
        lost = [Pose(header=header, child_frame_id=child, state=TrackingState.LOST)
                for child in self.tracks.update(pose.child_frame_id for pose in tracking)]
        for pose in tracking + lost:
            child = pose.child_frame_id
            if child not in self.publishers:
                self.publishers[child] = self.node.publisher(self.node.keys.pose(child), Pose, Role.RESULT)
            self.publishers[child].put(pose)


def run(node: Node, params: Params) -> None:
    try:
        rig, bodies = load(params)
    except ValueError as exc:
        raise NodeError(str(exc)) from exc
    if not bodies:
        node.log.info("no bodies file (bodies): every point is published unlabelled, no pose")
    for warning in check_bodies(bodies, params.match):
        node.log.warning("bodies: %s", warning)
    keys = node.keys
    infos = {} if rig is not None else {
        name: node.inbox(keys.camera_info(name), CameraInfo, Role.RESULT, depth=INFO_DEPTH) for name in params.cameras}
    calibration = Calibration(params.cameras, rig, infos)
    kernels.warm()
    sets = node.synced({name: keys.blobs(name) for name in params.cameras}, Blobs, Role.RESULT, by="seq",
                       depth=params.sync_depth, backlog=params.backlog)
    points_out = node.publisher(keys.points(), Points3D, Role.RESULT)
    poses = PosePublishers(node)
    names = list(bodies)
    per_set = BodiesPerSet(bodies, params)
    for joined in sets:
        first = joined[params.cameras[0]]
        header = first.header.model_copy(update={"frame_id": WORLD})
        cameras = calibration.current()
        if cameras is None:
            node.report("no_calibration", f"no CameraInfo for {', '.join(calibration.missing())} and no rig file: "
                        "nothing triangulated", keys.camera_info(calibration.missing()[0]))
            continue
        found, predicted = per_set.find(header.stamp_ns, cameras,
                                        [pixels(joined[name], params.flagged) for name in params.cameras],
                                        [split_parts(joined[name]) for name in params.cameras])
        poses.put(header, body_poses(header, found.matching) + predicted_poses(header, predicted))
        if points_out.matched():
            points_out.put(points_message(header, found.points, names, found.matching, found.covariances))
        per_set.learn(header.stamp_ns, found)
        calibration.refresh()


def _inputs(params: Params) -> tuple[str, ...]:
    infos = () if params.rig_file is not None else tuple(f"{name}/camera_info" for name in params.cameras)
    return (*(f"{name}/blobs" for name in params.cameras), *infos)


def _check(params: Params) -> None:
    load(params)


def _check_frames(params: Params, sizes: Callable[[], FrameSizes]) -> None:
    """Each camera of the rig file against the size of its frames, where the source tells it (``sizes()``):
    ValueError naming the file, the camera and both sizes when they differ. The file is used as it is,
    with no scaling to the frames, as blobs carry no frame size to scale it to."""
    if params.rig_file is None:
        return
    rig = read_rig(params.rig_file)
    for name in params.cameras:
        size = sizes().get(name)
        camera = rig.camera(name)
        if size is not None and (camera.width, camera.height) != size:
            raise ValueError(f"{params.rig_file}: camera {name} is calibrated for {camera.width}x{camera.height}, "
                             f"its frames are {size[0]}x{size[1]}: a rig file is used as it is (blob centroids "
                             f"are in the frames' pixels), use one made at {size[0]}x{size[1]}")


def _prepare() -> None:
    compiled.prepare(kernels.warm, "the rigid bodies node's kernels")


KIND = NodeKind(name="rigid_bodies", summary="rigid bodies' 6-DoF poses from the blobs of a calibrated rig's cameras",
                params=Params, run=run, inputs=_inputs, outputs=("points", "pose/body/**"), check=_check,
                check_frames=_check_frames, prepare=_prepare)
