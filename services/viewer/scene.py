"""Messages to Rerun rows: what each artrack message looks like in the viewer. No bus, no I/O.

``Scene.rows(message)`` returns the ``Row``s (entity path, archetypes) that draw one message,
at the paths ``services.viewer.layout`` describes; the caller logs them at the message's time
(``services.viewer.recording.ViewLog``). The live node and the offline converter feed the
same ``Scene``, so a recording converted afterwards looks like what was viewed live.

A ``Scene`` keeps what drawing needs across messages: the image rate gate, the last
calibration of each camera (a CameraInfo is logged only when it changes, though capture
publishes one per frame), the bounded trail of each posed frame, the entities already given
their static style (colours, sizes), the transforms each source's last GroundTruth listed,
and the cameras seen so far (``cameras``, in order of appearance, for the blueprint).

Poses in state ``tracking`` or ``predicted`` are drawn; any other state (lost, initialising,
no calibration) clears the pose's entity, so stale axes do not linger, and adds nothing to
its trajectory. A transform that a source's previous GroundTruth listed and its current one
does not (a marker that left the view) is cleared the same way, and so is a detection
overlay by a message with zero rows.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
import rerun as rr
from pydantic import BaseModel, ConfigDict, Field, field_validator

from protocol.detections import Blobs, Keypoints, MarkerDetections
from protocol.maps import Keyframes, PointCloud
from protocol.message import Message
from protocol.mocap import Points3D
from protocol.poses import GroundTruth, Pose, RigidBodies
from protocol.sensors import CameraInfo, Image
from protocol.spatial import Transform
from protocol.system import ErrorReport, NodeStats, StageTimings
from protocol.tracking_state import TrackingState
from services.viewer import layout
from services.viewer.images import RateGate, image_archetype

DRAWN_STATES = frozenset({TrackingState.TRACKING, TrackingState.RECOGNISED, TrackingState.PREDICTED})
STYLES = {
    "markers": rr.LineStrips2D.from_fields(colors=0x00DC5AFF),
    "keypoints": rr.Points2D.from_fields(colors=0xFFC800FF, radii=rr.Radius.ui_points(2.0)),
    layout.CLEAN_BLOBS: rr.Points2D.from_fields(colors=0x00C8FFC0),
    layout.FLAGGED_BLOBS: rr.Points2D.from_fields(colors=0xFF3CC8C0),
    layout.LABELLED: rr.Points3D.from_fields(colors=0x00C8FFFF, radii=rr.Radius.ui_points(4.0)),
    layout.UNLABELLED: rr.Points3D.from_fields(colors=0xFF3CC8FF, radii=rr.Radius.ui_points(4.0)),
    layout.ESTIMATE: rr.LineStrips3D.from_fields(colors=0xFF8C00FF),
    layout.TRUTH: rr.LineStrips3D.from_fields(colors=0x3CC83CFF),
}
"""Colours (RGBA) and sizes, logged once per entity as static rows: per-row colours cost more than the data."""
AXIS_COLOURS = np.array([[255, 0, 0], [0, 200, 0], [0, 80, 255]], np.uint8)
"""RGB of a frame's x, y and z axes, as Rerun draws a transform's."""


class ViewOptions(BaseModel):
    """How messages are drawn (shared by the viewer node and ``artrack view``)."""

    model_config = ConfigDict(extra="forbid")
    FLAGS: ClassVar[dict[str, str]] = {"jpeg_quality": "jpeg", "trajectory_length": "trajectory"}

    image_hz: float = Field(default=0.0, ge=0, description="at most this many images per camera per second "
                                                           "of frame time; 0 = every frame")
    jpeg_quality: int = Field(default=0, ge=0, le=100, description="0 = raw pixels; 1-100 = JPEG of that quality")
    trajectory_length: int = Field(default=300, ge=0, le=100_000,
                                   description="positions kept in each trajectory line; 0 = no trajectories")
    axis_length_m: float = Field(default=0.1, gt=0, description="length of the axes drawn at each pose (m)")
    world_axes: str = Field(default="RDF", description="what the world frame's x, y, z point at, in Rerun's "
                                                       "letters: RDF (OpenCV camera axes), RFU or FLU (z up), ...")

    @field_validator("world_axes")
    @classmethod
    def _known_axes(cls, value: str) -> str:
        if not isinstance(getattr(rr.ViewCoordinates, value, None), rr.components.ViewCoordinates):
            raise ValueError(f"{value!r} is not one of Rerun's view coordinates (RDF, RFU, FLU, RUB, ...)")
        return value


@dataclass(frozen=True)
class Row:
    """Archetypes to log at one entity path (``static``: timeless)."""

    entity: str
    archetypes: tuple[Any, ...]
    static: bool = False


def error_text(report: ErrorReport) -> str:
    """One line saying what a node skipped, where, and how often so far."""
    where = f" on {report.key}" if report.key else ""
    return f"{report.kind}{where}: {report.detail} ({report.count} so far)"


def frame_seq(message: Message) -> int | None:
    """The ``seq`` timeline value of ``message``: its frame's number; None for node health."""
    return None if isinstance(message, NodeStats | ErrorReport) else message.header.seq


class Scene:
    """The rows that draw each message (see the module docstring)."""

    def __init__(self, options: ViewOptions):
        self.options = options
        self.cameras: list[str] = []
        self._gate = RateGate(options.image_hz)
        self._calibrations: dict[str, tuple] = {}
        self._trails: dict[str, Trail] = {}
        self._styled: set[str] = set()
        self._known_truth: dict[str, set[tuple[str, str]]] = {}
        self._draw: dict[type[Message], Callable[[Any], list[Row]]] = {
            Image: self._image, CameraInfo: self._camera_info, MarkerDetections: self._markers,
            Blobs: self._blobs, Keypoints: self._keypoints, Pose: self._pose, RigidBodies: self._bodies,
            GroundTruth: self._truth, PointCloud: self._cloud, NodeStats: self._stats, ErrorReport: self._error,
            Points3D: self._points, Keyframes: self._keyframes, StageTimings: self._stages,
        }

    def setup(self) -> list[Row]:
        """Timeless rows logged once, before any message."""
        return [Row(layout.WORLD, (getattr(rr.ViewCoordinates, self.options.world_axes),), static=True)]

    def rows(self, message: Message) -> list[Row]:
        """The rows that draw ``message``; none for a message the viewer does not draw or holds back."""
        draw = self._draw.get(type(message))
        return draw(message) if draw is not None else []

    def _camera(self, message: Message) -> str:
        camera = layout.camera(message.header.frame_id)
        if camera not in self.cameras:
            self.cameras.append(camera)
        return camera

    def _image(self, image: Image) -> list[Row]:
        entity = layout.image(self._camera(image))
        if not self._gate.admit(entity, image.header.stamp_ns):
            return []
        return [Row(entity, (image_archetype(image, self.options.jpeg_quality),))]

    def _camera_info(self, info: CameraInfo) -> list[Row]:
        camera = self._camera(info)
        placed = info.T_rig_camera
        calibration = (info.k, info.width, info.height, placed)
        if self._calibrations.get(camera) == calibration:
            return []
        self._calibrations[camera] = calibration
        pinhole = rr.Pinhole(image_from_camera=np.reshape(info.k, (3, 3)), resolution=[info.width, info.height],
                             camera_xyz=rr.ViewCoordinates.RDF)
        return [Row(layout.frame(camera), (_transform(placed),)), Row(layout.image(camera), (pinhole,))]

    def _styled_row(self, entity: str, style: str, archetype: Any) -> list[Row]:
        """``archetype`` at ``entity``, preceded the first time by the entity's static style."""
        rows = [Row(entity, (archetype,))]
        if entity not in self._styled:
            self._styled.add(entity)
            rows.insert(0, Row(entity, (STYLES[style],), static=True))
        return rows

    def _markers(self, markers: MarkerDetections) -> list[Row]:
        outlines = np.concatenate([markers.corners, markers.corners[:, :1]], axis=1)  # (N, 5, 2): closed
        strips = rr.LineStrips2D(outlines, labels=[str(i) for i in markers.ids])
        return self._styled_row(layout.detections(self._camera(markers), "markers"), "markers", strips)

    def _blobs(self, blobs: Blobs) -> list[Row]:
        """Blobs without flags and flagged blobs (merged, occluded, clipped) in two colours."""
        camera = self._camera(blobs)
        flagged = blobs.flags != 0
        return [row for kind, rows in ((layout.CLEAN_BLOBS, ~flagged), (layout.FLAGGED_BLOBS, flagged))
                for row in self._styled_row(layout.detections(camera, kind), kind,
                                            rr.Points2D(blobs.centroids[rows], radii=blobs.radii[rows]))]

    def _points(self, points: Points3D) -> list[Row]:
        """Triangulated points, those matched to a body (labelled with its name) apart from the others."""
        base = layout.points(layout.frame(points.header.frame_id))
        labelled = points.body >= 0
        names = [points.bodies[i] for i in points.body[labelled]]
        return [*self._styled_row(f"{base}/{layout.LABELLED}", layout.LABELLED,
                                  rr.Points3D(points.points[labelled], labels=names)),
                *self._styled_row(f"{base}/{layout.UNLABELLED}", layout.UNLABELLED,
                                  rr.Points3D(points.points[~labelled]))]

    def _keypoints(self, keypoints: Keypoints) -> list[Row]:
        points = rr.Points2D(keypoints.points)
        return self._styled_row(layout.detections(self._camera(keypoints), "keypoints"), "keypoints", points)

    def _pose(self, pose: Pose) -> list[Row]:
        drawn = pose.transform if pose.state in DRAWN_STATES else None
        return self._posed(layout.frame(pose.header.frame_id), pose.child_frame_id, drawn, layout.ESTIMATE)

    def _bodies(self, bodies: RigidBodies) -> list[Row]:
        parent = layout.frame(bodies.header.frame_id)
        return [row for body in bodies.bodies
                for row in self._posed(parent, f"body/{body.name}",
                                       body.transform if body.state in DRAWN_STATES else None, layout.ESTIMATE)]

    def _truth(self, truth: GroundTruth) -> list[Row]:
        rows, known = [], set()
        for fact in truth.transforms:
            parent = layout.frame(fact.parent_frame)
            rows += self._posed(parent, fact.child_frame, fact.transform, layout.TRUTH)
            known.add((parent, fact.child_frame))
        gone = self._known_truth.get(truth.header.frame_id, set()) - known
        self._known_truth[truth.header.frame_id] = known
        return rows + [row for parent, child in sorted(gone)
                       for row in self._posed(parent, child, None, layout.TRUTH)]

    def _posed(self, parent: str, child: str, transform: Transform | None, source: str) -> list[Row]:
        """``T_parent_child`` drawn from ``source`` (``layout.ESTIMATE`` or ``TRUTH``); None clears it."""
        entity = layout.pose(parent, child, source)
        if transform is None:
            return [Row(entity, (rr.Clear(recursive=False),))]
        rows = [Row(entity, (_transform(transform), rr.TransformAxes3D(self.options.axis_length_m)))]
        if self.options.trajectory_length:
            path = layout.trajectory(parent, child, source)
            trail = self._trails.get(path)
            if trail is None:
                trail = self._trails[path] = Trail(self.options.trajectory_length)
            rows += self._styled_row(path, source, rr.LineStrips3D(trail.add(transform.translation)[None]))
        return rows

    def _cloud(self, cloud: PointCloud) -> list[Row]:
        colors = cloud.colors[:, ::-1] if len(cloud.colors) else None  # BGR -> RGB
        return [Row(layout.points(layout.frame(cloud.header.frame_id)), (rr.Points3D(cloud.points, colors=colors),))]

    def _keyframes(self, keyframes: Keyframes) -> list[Row]:
        """Each keyframe's axes: three arrows from its centre, ``axis_length_m`` long, red x, green y, blue z."""
        entity = layout.keyframes(layout.frame(keyframes.header.frame_id), keyframes.child_frame_id)
        axes = keyframes.poses[:, :3, :3].transpose(0, 2, 1) * self.options.axis_length_m  # (K, 3 axes, 3)
        origins = np.repeat(keyframes.poses[:, :3, 3], 3, axis=0)
        colours = np.tile(AXIS_COLOURS, (len(keyframes.poses), 1))
        return [Row(entity, (rr.Arrows3D(origins=origins, vectors=axes.reshape(-1, 3), colors=colours),))]

    def _stages(self, timings: StageTimings) -> list[Row]:
        camera = self._camera(timings)
        return [Row(layout.stats(layout.STAGE_MS, camera, stage), (rr.Scalars(ms),))
                for stage, ms in timings.stages_ms.items()]

    def _stats(self, stats: NodeStats) -> list[Row]:
        node = stats.node
        figures = [(layout.stats(layout.DROPPED, node), stats.dropped),
                   (layout.stats(layout.DECODE_ERRORS, node), stats.decode_errors),
                   (layout.stats(layout.PROCESSING_MS, node, "p50"), stats.processing_ms_p50),
                   (layout.stats(layout.PROCESSING_MS, node, "p99"), stats.processing_ms_p99),
                   (layout.stats(layout.LATENCY_MS, node, "p50"), stats.latency_ms_p50),
                   (layout.stats(layout.LATENCY_MS, node, "p99"), stats.latency_ms_p99)]
        figures += [(layout.stats(layout.RATE_HZ, node, s.direction, s.key), s.rate_hz) for s in stats.streams]
        return [Row(entity, (rr.Scalars(value),)) for entity, value in figures if value is not None]

    def _error(self, report: ErrorReport) -> list[Row]:
        return [Row(layout.log(report.node), (rr.TextLog(error_text(report), level=rr.TextLogLevel.WARN),))]


class Trail:
    """The last ``length`` positions of a frame, always contiguous: a window sliding over a buffer
    twice as long, moved back to its start once it reaches the end (amortised O(1) per point)."""

    def __init__(self, length: int):
        self.length = length
        self._buffer = np.empty((2 * length, 3), np.float32)
        self._start = self._end = 0

    def add(self, position: tuple[float, float, float]) -> np.ndarray:
        """Append ``position``; the window, (n, 3) float32, oldest first (a view: read before the next add)."""
        if self._end == len(self._buffer):
            kept = self.length - 1
            self._buffer[:kept] = self._buffer[self._end - kept:self._end]
            self._start, self._end = 0, kept
        self._buffer[self._end] = position
        self._end += 1
        self._start = max(self._start, self._end - self.length)
        return self._buffer[self._start:self._end]


def _transform(transform: Transform) -> rr.Transform3D:
    """``T_parent_child`` as Rerun's child-to-parent transform."""
    return rr.Transform3D(translation=transform.translation, quaternion=rr.Quaternion(xyzw=transform.rotation))
