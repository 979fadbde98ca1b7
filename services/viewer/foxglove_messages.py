"""artrack messages as Foxglove's well-known messages (``foxglove.messages``, protobuf): no I/O.

One function per artrack message type returns the Foxglove messages that show it, and a
``FoxgloveConversion`` (one per file or server) gives each its topic. Frames keep artrack's names
(``cam0``, ``world``, ``rig``, ``marker/7``, ``body/wand``); lengths are metres, pixel coordinates are x
right, y down with the centre of the top-left pixel at (0, 0), as in artrack and in Foxglove's image
panel. Every message is stamped with its artrack header's ``stamp_ns`` (the capture time of the frame it
comes from), so detections line up with their image.

Topics are named from the message itself, so a recording exported afterwards and the live server
show the same topics:

* ``/<camera>/image``: ``Image`` as ``RawImage`` (``CompressedImage``, JPEG; PNG for mono16, when
  ``compressed``); an AR overlay (frame id ``<camera>/overlay``) lands on ``/<camera>/overlay/image``.
* ``/<camera>/camera_info``: ``CameraInfo`` as ``CameraCalibration`` in the image's frame, and its
  ``T_rig_camera`` as ``rig -> <camera>`` on ``/tf``, with ``world -> rig`` (the identity: for a tracker a
  fixed rig's frame is the world its bodies and points are in).
* ``/<camera>/markers``, ``/<camera>/blobs``, ``/<camera>/keypoints``: detections as
  ``ImageAnnotations`` (marker outlines with their ids, blobs as circles of their radius, keypoints
  as points); ``/<camera>/marker_outlines``: each marker of known side as a square ``SceneUpdate``
  entity in its own frame ``marker/<id>``, drawn wherever its pose places it.
* ``/<camera>/target_outlines``: ``ImageTargets`` (the image targets a features node poses in the camera's
  frames) as one ``SceneUpdate`` entity per target in its own frame ``target/<name>``: the printed image's
  outline through its four corners and a translucent plane over it, drawn wherever the target's pose
  places it.
* ``/pose/<parent>/<child>``: ``Pose`` as ``PoseInFrame``, and ``parent -> child`` on ``/tf`` (camera
  -> markers and targets, map -> the SLAM camera, world -> bodies).
* ``/tf``: ``RigidBodies`` as ``world -> body/<name>``; ``/tf_static``: ``StaticTransforms``.
* ``/tf`` and ``/tf_static`` are one tree, every frame with one parent (``services.geometry.transform_tree``):
  an edge that would give a frame a second parent is turned round when it can be (a SLAM camera placed on
  its rig: ``map -> cam0`` goes out as ``cam0 -> map``, the inverse, so the map hangs under the camera), else
  it names a child of its own (a marker seen by a second camera: ``cam1 -> cam1/marker/3``).
* ``/<frame>/truth``: ``GroundTruth`` as ``FrameTransforms`` whose children are renamed
  ``truth/<child>``, so the truth stands beside the estimate instead of giving a frame two parents.
* ``/<frame>/points``: ``Points3D`` as a ``PointCloud``; ``/<frame>/spheres``: the same points as
  spheres (matched to a body: cyan, with the body's name as entity id; the others: magenta).
* ``/<frame>/map``: ``PointCloud`` (SLAM map points) as a ``PointCloud`` with their colours.
* ``/<frame>/trajectory/<child>``: ``Trajectory`` (a SLAM map's final trajectory) as ``PosesInFrame``.
* ``/log``: ``ErrorReport`` as a warning ``Log`` named after its node.

Poses and bodies in a state other than tracking, recognised or predicted have no transform to
show and give nothing. Node statistics, stage timings and keyframes have no Foxglove schema and
are left out.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from foxglove.messages import (
    CameraCalibration,
    CircleAnnotation,
    Color,
    CompressedImage,
    FrameTransform,
    FrameTransforms,
    ImageAnnotations,
    LinePrimitive,
    LinePrimitiveLineType,
    Log,
    LogLevel,
    PackedElementField,
    PackedElementFieldNumericType,
    Point2,
    Point3,
    PointCloud,
    PointsAnnotation,
    PointsAnnotationType,
    Pose,
    PoseInFrame,
    PosesInFrame,
    Quaternion,
    RawImage,
    SceneEntity,
    SceneUpdate,
    SpherePrimitive,
    TextAnnotation,
    Timestamp,
    TriangleListPrimitive,
    Vector3,
)

from protocol import detections, maps, mocap, poses, sensors, spatial, system, targets
from protocol.message import Message
from services.convert import in_tree
from services.geometry.se3 import to_quaternion_translation
from services.geometry.transform_tree import TransformTree
from services.viewer.scene import DRAWN_STATES, error_text

FoxgloveMessage = (RawImage | CompressedImage | CameraCalibration | FrameTransforms | PoseInFrame | PosesInFrame
                   | PointCloud | SceneUpdate | ImageAnnotations | Log)
Topical = tuple[str, FoxgloveMessage]
"""A Foxglove message with the topic it goes on."""

TF, TF_STATIC, LOG = "/tf", "/tf_static", "/log"
TRUTH_PREFIX = "truth/"
MARKER_COLOUR = Color(r=0.0, g=0.86, b=0.35, a=1.0)
KEYPOINT_COLOUR = Color(r=1.0, g=0.78, b=0.0, a=1.0)
TARGET_PLANE_COLOUR = Color(r=0.0, g=0.86, b=0.35, a=0.2)
CLEAN_COLOUR = Color(r=0.0, g=0.78, b=1.0, a=0.75)
FLAGGED_COLOUR = Color(r=1.0, g=0.24, b=0.78, a=0.75)
"""RGBA in [0, 1], the Rerun viewer's colours: markers green, keypoints amber, blobs and points cyan
(clean, labelled) or magenta (flagged, unlabelled); image targets' outlines as markers', their planes translucent."""
_ENCODINGS = {"mono8": ("mono8", 1), "mono16": ("mono16", 2), "bgr8": ("bgr8", 3), "bgra8": ("bgra8", 4)}
"""artrack image encoding -> (Foxglove RawImage encoding, bytes per pixel)."""
_DISTORTION = {"plumb_bob": "plumb_bob", "rational_polynomial": "rational_polynomial",
               "equidistant": "kannala_brandt"}
_F32 = PackedElementFieldNumericType.Float32
_U8 = PackedElementFieldNumericType.Uint8


@dataclass(frozen=True)
class FoxgloveOptions:
    """``compressed``: images as JPEG (``jpeg_quality``, 1-100; mono16 as PNG) instead of raw pixels;
    ``sphere_m``: diameter of the spheres drawn at triangulated points (m)."""

    compressed: bool = False
    jpeg_quality: int = 90
    sphere_m: float = 0.015


DEFAULT_OPTIONS = FoxgloveOptions()

def timestamp(stamp_ns: int) -> Timestamp:
    """``stamp_ns`` (ns since the epoch) as Foxglove's seconds and nanoseconds."""
    sec, nsec = divmod(stamp_ns, 1_000_000_000)
    return Timestamp(sec, nsec)


def raw_image(image: sensors.Image) -> RawImage:
    """The frame's pixels unchanged (mono8, mono16 little-endian, bgr8, bgra8), rows packed (step = width x
    bytes per pixel), in the camera's optical frame ``header.frame_id``."""
    encoding, pixel_bytes = _ENCODINGS[image.encoding]
    pixels = image.data.astype("<u2", copy=False) if image.encoding == "mono16" else image.data
    return RawImage(timestamp=timestamp(image.header.stamp_ns), frame_id=image.header.frame_id, width=image.width,
                    height=image.height, encoding=encoding, step=image.width * pixel_bytes,
                    data=np.ascontiguousarray(pixels).tobytes())


def compressed_image(image: sensors.Image, jpeg_quality: int = 90) -> CompressedImage:
    """The frame as a JPEG of ``jpeg_quality`` (bgra8 loses its alpha), or a PNG for mono16 (JPEG holds 8 bits)."""
    if image.encoding == "mono16":
        ok, encoded = cv2.imencode(".png", image.data)
        image_format = "png"
    else:
        pixels = cv2.cvtColor(image.data, cv2.COLOR_BGRA2BGR) if image.encoding == "bgra8" else image.data
        ok, encoded = cv2.imencode(".jpg", pixels, [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality])
        image_format = "jpeg"
    if not ok:
        raise ValueError(f"OpenCV could not encode a {image.width}x{image.height} {image.encoding} frame")
    return CompressedImage(timestamp=timestamp(image.header.stamp_ns), frame_id=image.header.frame_id,
                           data=encoded.tobytes(), format=image_format)


def camera_calibration(info: sensors.CameraInfo) -> CameraCalibration:
    """Intrinsics in the image's frame ``header.frame_id``: K, R (3x3) and P (3x4) row-major, D in OpenCV's
    order; ``equidistant`` is Foxglove's ``kannala_brandt``. Without a P, P = [K | 0]."""
    k = list(info.k)
    p = list(info.p) if info.p is not None else [*k[0:3], 0.0, *k[3:6], 0.0, *k[6:9], 0.0]
    return CameraCalibration(timestamp=timestamp(info.header.stamp_ns), frame_id=info.header.frame_id,
                             width=info.width, height=info.height,
                             distortion_model=_DISTORTION[info.distortion_model], D=list(info.d), K=k,
                             R=list(info.r), P=p)


def frame_transform(parent: str, child: str, transform: spatial.Transform, stamp_ns: int) -> FrameTransform:
    """``T_parent_child`` (m, unit quaternion x y z w): Foxglove's transform from ``parent`` to ``child``."""
    (x, y, z), (qx, qy, qz, qw) = transform.translation, transform.rotation
    return FrameTransform(timestamp=timestamp(stamp_ns), parent_frame_id=parent, child_frame_id=child,
                          translation=Vector3(x=x, y=y, z=z), rotation=Quaternion(x=qx, y=qy, z=qz, w=qw))


def transforms(edges: list[spatial.FrameTransform], stamp_ns: int) -> FrameTransforms:
    """Each ``T_parent_child`` of ``edges``, stamped ``stamp_ns``."""
    return FrameTransforms(transforms=[frame_transform(edge.parent_frame, edge.child_frame, edge.transform, stamp_ns)
                                       for edge in edges])


def camera_placement(info: sensors.CameraInfo) -> list[spatial.FrameTransform]:
    """``world -> rig`` (the identity: a fixed rig's frame is the world, where bodies and points are) and
    ``rig -> <camera>``, where the camera sits in its rig (``T_rig_camera``)."""
    return [spatial.FrameTransform(parent_frame=spatial.WORLD_FRAME, child_frame=spatial.RIG_FRAME,
                                   transform=spatial.Transform()),
            spatial.FrameTransform(parent_frame=spatial.RIG_FRAME, child_frame=info.header.frame_id,
                                   transform=info.T_rig_camera)]


def pose_in_frame(pose: poses.Pose) -> PoseInFrame:
    """The child's pose in ``header.frame_id``: position (m) and orientation of ``T_parent_child``."""
    (x, y, z), (qx, qy, qz, qw) = pose.transform.translation, pose.transform.rotation
    return PoseInFrame(timestamp=timestamp(pose.header.stamp_ns), frame_id=pose.header.frame_id,
                       pose=Pose(position=Vector3(x=x, y=y, z=z), orientation=Quaternion(x=qx, y=qy, z=qz, w=qw)))


def trajectory_poses(trajectory: maps.Trajectory) -> PosesInFrame:
    """Every frame's final pose (position, m, and orientation of ``T_map_camera``) in ``header.frame_id``."""
    shown = []
    for T in trajectory.poses:
        (qx, qy, qz, qw), (x, y, z) = (v.tolist() for v in to_quaternion_translation(T))
        shown.append(Pose(position=Vector3(x=x, y=y, z=z), orientation=Quaternion(x=qx, y=qy, z=qz, w=qw)))
    return PosesInFrame(timestamp=timestamp(trajectory.header.stamp_ns), frame_id=trajectory.header.frame_id,
                        poses=shown)


def pose_edge(pose: poses.Pose) -> list[spatial.FrameTransform]:
    """``header.frame_id -> child_frame_id`` (camera -> marker or target, map -> SLAM camera, world -> body)."""
    return [spatial.FrameTransform(parent_frame=pose.header.frame_id, child_frame=pose.child_frame_id,
                                   transform=pose.transform)]


def body_edges(bodies: poses.RigidBodies) -> list[spatial.FrameTransform]:
    """``world -> body/<name>`` of each body with a pose to show (tracking, recognised, predicted)."""
    return [spatial.FrameTransform(parent_frame=bodies.header.frame_id, child_frame=f"body/{body.name}",
                                   transform=body.transform) for body in bodies.bodies if body.state in DRAWN_STATES]


def truth_transforms(truth: poses.GroundTruth) -> FrameTransforms:
    """Each exact ``T_parent_child`` as ``parent -> truth/<child>``."""
    return FrameTransforms(transforms=[
        frame_transform(fact.parent_frame, TRUTH_PREFIX + fact.child_frame, fact.transform, truth.header.stamp_ns)
        for fact in truth.transforms])


def _placed_at(x: float, y: float, z: float) -> Pose:
    """A pose at (x, y, z) (m) with the parent frame's axes."""
    return Pose(position=Vector3(x=x, y=y, z=z), orientation=Quaternion(x=0.0, y=0.0, z=0.0, w=1.0))


def _cloud(stamp_ns: int, frame_id: str, points: np.ndarray, colours: np.ndarray | None) -> PointCloud:
    """(N, 3) points (m) packed as float32 x, y, z, then uint8 red, green, blue, alpha when ``colours`` (N, 3)
    RGB are given."""
    fields = [PackedElementField(name=axis, offset=4 * i, type=_F32) for i, axis in enumerate("xyz")]
    if colours is None:
        packed = np.ascontiguousarray(points, "<f4")
        stride = 12
    else:
        layout = np.dtype([("xyz", "<f4", 3), ("rgba", "u1", 4)])
        packed = np.empty(len(points), layout)
        packed["xyz"] = points
        packed["rgba"][:, :3] = colours
        packed["rgba"][:, 3] = 255
        fields += [PackedElementField(name=name, offset=12 + i, type=_U8)
                   for i, name in enumerate(("red", "green", "blue", "alpha"))]
        stride = 16
    return PointCloud(timestamp=timestamp(stamp_ns), frame_id=frame_id,
                      pose=_placed_at(0.0, 0.0, 0.0), point_stride=stride,
                      fields=fields, data=packed.tobytes())


def triangulated_cloud(points: mocap.Points3D) -> PointCloud:
    """The triangulated points in ``header.frame_id``, float32 x y z (m), 12 bytes each."""
    return _cloud(points.header.stamp_ns, points.header.frame_id, points.points, None)


def map_cloud(cloud: maps.PointCloud) -> PointCloud:
    """Map points in ``header.frame_id``: float32 x y z (m), then their colours (RGB, alpha 255) if they have any."""
    colours = cloud.colors[:, ::-1] if len(cloud.colors) else None  # BGR -> RGB
    return _cloud(cloud.header.stamp_ns, cloud.header.frame_id, cloud.points, colours)


def body_spheres(points: mocap.Points3D, diameter_m: float = 0.015) -> SceneUpdate:
    """The triangulated points as spheres of ``diameter_m``: one entity per body (id ``body/<name>``, cyan) with
    the points matched to it, one (id ``unlabelled``, magenta) with the others; every entity is replaced by the
    next message's (an emptied one is sent empty)."""
    groups = [(f"body/{name}", points.body == i, CLEAN_COLOUR) for i, name in enumerate(points.bodies)]
    groups.append(("unlabelled", points.body < 0, FLAGGED_COLOUR))
    size = Vector3(x=diameter_m, y=diameter_m, z=diameter_m)
    stamp = timestamp(points.header.stamp_ns)
    return SceneUpdate(entities=[
        SceneEntity(timestamp=stamp, frame_id=points.header.frame_id, id=entity, spheres=[
            SpherePrimitive(pose=_placed_at(x, y, z), size=size,
                            color=colour) for x, y, z in points.points[rows].tolist()])
        for entity, rows, colour in groups])


def marker_outlines(markers: detections.MarkerDetections) -> SceneUpdate:
    """Each marker of known side ``s`` (m) as a closed square (-s/2..s/2, z = 0, OpenCV's marker model) in its
    own frame ``marker/<id>``, locked to that frame; id ``marker/<id>``."""
    stamp = timestamp(markers.header.stamp_ns)
    entities = []
    for marker, side in zip(markers.ids.tolist(), markers.side_m.tolist(), strict=True):
        if side <= 0:
            continue
        h = side / 2
        square = [Point3(x=-h, y=h), Point3(x=h, y=h), Point3(x=h, y=-h), Point3(x=-h, y=-h)]
        outline = LinePrimitive(type=LinePrimitiveLineType.LineLoop, pose=_placed_at(0.0, 0.0, 0.0),
                                thickness=0.002, points=square, color=MARKER_COLOUR)
        entities.append(SceneEntity(timestamp=stamp, frame_id=f"marker/{marker}", id=f"marker/{marker}",
                                    frame_locked=True, lines=[outline]))
    return SceneUpdate(entities=entities)


def target_outlines(described: targets.ImageTargets) -> SceneUpdate:
    """Each image target as an entity in its own frame (``frame_id``, e.g. ``target/<name>``), locked to that frame,
    id the frame's name: its outline, a closed line through its ``corners`` (m, in that frame: ``(+-w/2, +-h/2, 0)``
    for artrack's targets), and a translucent plane over the same rectangle (two triangles). Static: the entities
    last until replaced."""
    stamp = timestamp(described.header.stamp_ns)
    origin = _placed_at(0.0, 0.0, 0.0)
    entities = []
    for target in described.targets:
        corners = [Point3(x=x, y=y, z=z) for x, y, z in target.corners]
        outline = LinePrimitive(type=LinePrimitiveLineType.LineLoop, pose=origin, thickness=0.003, points=corners,
                                color=MARKER_COLOUR)
        plane = TriangleListPrimitive(pose=origin, points=corners, color=TARGET_PLANE_COLOUR,
                                      indices=[0, 1, 2, 0, 2, 3])
        entities.append(SceneEntity(timestamp=stamp, frame_id=target.frame_id, id=target.frame_id, frame_locked=True,
                                    lines=[outline], triangles=[plane]))
    return SceneUpdate(entities=entities)


def marker_annotations(markers: detections.MarkerDetections) -> ImageAnnotations:
    """Each marker's four corners (px) as a closed outline, and its id written at its first corner."""
    stamp = timestamp(markers.header.stamp_ns)
    outlines = [PointsAnnotation(timestamp=stamp, type=PointsAnnotationType.LineLoop,
                                 points=[Point2(x=x, y=y) for x, y in corners], outline_color=MARKER_COLOUR,
                                 thickness=2.0) for corners in markers.corners.tolist()]
    labels = [TextAnnotation(timestamp=stamp, position=Point2(x=corners[0][0], y=corners[0][1]), text=str(marker),
                             font_size=14.0, text_color=MARKER_COLOUR)
              for marker, corners in zip(markers.ids.tolist(), markers.corners.tolist(), strict=True)]
    return ImageAnnotations(timestamp=stamp, points=outlines, texts=labels)


def blob_annotations(blobs: detections.Blobs) -> ImageAnnotations:
    """Each blob as a circle of its radius (px) at its centroid: cyan, or magenta when flagged."""
    stamp = timestamp(blobs.header.stamp_ns)
    return ImageAnnotations(timestamp=stamp, circles=[
        CircleAnnotation(timestamp=stamp, position=Point2(x=x, y=y), diameter=2.0 * radius, thickness=1.5,
                         outline_color=FLAGGED_COLOUR if flags else CLEAN_COLOUR)
        for (x, y), radius, flags in zip(blobs.centroids.tolist(), blobs.radii.tolist(), blobs.flags.tolist(),
                                         strict=True)])


def keypoint_annotations(keypoints: detections.Keypoints) -> ImageAnnotations:
    """The keypoints (px) as one set of points."""
    stamp = timestamp(keypoints.header.stamp_ns)
    points = PointsAnnotation(timestamp=stamp, type=PointsAnnotationType.Points,
                              points=[Point2(x=x, y=y) for x, y in keypoints.points.tolist()],
                              outline_color=KEYPOINT_COLOUR, thickness=3.0)
    return ImageAnnotations(timestamp=stamp, points=[points])


def log_entry(report: system.ErrorReport) -> Log:
    """What a node skipped, as a warning named after the node."""
    return Log(timestamp=timestamp(report.header.stamp_ns), level=LogLevel.Warning, message=error_text(report),
               name=report.node)


class FoxgloveConversion:
    """artrack messages of one recording or one live rig, in the order they come, as the Foxglove messages that
    show them, each with its topic (see the module docstring). Transforms go through one ``TransformTree``, so
    ``/tf`` and ``/tf_static`` give every frame a single parent."""

    def __init__(self, options: FoxgloveOptions = DEFAULT_OPTIONS):
        self.options = options
        self.tree = TransformTree()

    def __call__(self, message: Message) -> list[Topical]:
        """What shows ``message``; none for a type without a Foxglove counterpart."""
        frame, stamp_ns = message.header.frame_id, message.header.stamp_ns
        match message:
            case sensors.Image():
                options = self.options
                image = compressed_image(message, options.jpeg_quality) if options.compressed else raw_image(message)
                return [(f"/{frame}/image", image)]
            case sensors.CameraInfo():
                return [(f"/{frame}/camera_info", camera_calibration(message)),
                        (TF, self._tree(camera_placement(message), stamp_ns))]
            case spatial.StaticTransforms():
                return [(TF_STATIC, self._tree(list(message.transforms), stamp_ns))]
            case poses.Pose():
                if message.state not in DRAWN_STATES:
                    return []
                return [(f"/pose/{frame}/{message.child_frame_id}", pose_in_frame(message)),
                        (TF, self._tree(pose_edge(message), stamp_ns))]
            case poses.RigidBodies():
                return [(TF, self._tree(body_edges(message), stamp_ns))]
            case poses.GroundTruth():
                return [(f"/{frame}/truth", truth_transforms(message))]
            case mocap.Points3D():
                return [(f"/{frame}/points", triangulated_cloud(message)),
                        (f"/{frame}/spheres", body_spheres(message, self.options.sphere_m))]
            case maps.PointCloud():
                return [(f"/{frame}/map", map_cloud(message))]
            case maps.Trajectory():
                return [(f"/{frame}/trajectory/{message.child_frame_id}", trajectory_poses(message))]
            case detections.MarkerDetections():
                return [(f"/{frame}/markers", marker_annotations(message)),
                        (f"/{frame}/marker_outlines", marker_outlines(message))]
            case targets.ImageTargets():
                return [(f"/{frame}/target_outlines", target_outlines(message))]
            case detections.Blobs():
                return [(f"/{frame}/blobs", blob_annotations(message))]
            case detections.Keypoints():
                return [(f"/{frame}/keypoints", keypoint_annotations(message))]
            case system.ErrorReport():
                return [(LOG, log_entry(message))]
        return []

    def _tree(self, edges: list[spatial.FrameTransform], stamp_ns: int) -> FrameTransforms:
        return transforms(in_tree(self.tree, edges), stamp_ns)
