"""A whole recording as a ROS 2 bag (MCAP storage, CDR messages), written without a ROS install (``rosbags``).

Each artrack message becomes the standard ROS 2 message that carries the same thing:

==========================  =================================  ===========================================
artrack                     ROS 2 type                         topic (keys relative to ``namespace/rig``)
==========================  =================================  ===========================================
``Image``                   ``sensor_msgs/msg/Image``          ``<camera>/image`` -> ``/<camera>/image_raw``;
                                                               other image keys keep their name
``CameraInfo``              ``sensor_msgs/msg/CameraInfo``     ``/<camera>/camera_info``
``Pose``                    ``geometry_msgs/msg/PoseStamped``  ``/pose/...`` (one topic per pose key), and
                            ``tf2_msgs/msg/TFMessage``         each one a transform on ``/tf``
``RigidBodies``             ``tf2_msgs/msg/TFMessage``         ``/tf``
``StaticTransforms``        ``tf2_msgs/msg/TFMessage``         ``/tf_static`` (transient local, as tf2's), and
                                                               each camera's ``T_rig_camera`` (its first
                                                               ``CameraInfo``'s): parent ``rig``
``GroundTruth``             ``tf2_msgs/msg/TFMessage``         ``/<camera>/truth`` (not ``/tf``: the truth
                                                               would fight the estimates for the frames)
``Points3D``, ``PointCloud``  ``sensor_msgs/msg/PointCloud2``  ``/points``, ``/map``, ``/<camera>/map``
==========================  =================================  ===========================================

Frames keep their artrack names (``cam0``, ``world``, ``rig``, ``marker/7``). An artrack camera frame is
OpenCV's (x right, y down, z forward), which is ROS's *optical* frame convention (REP 103's ``_optical``
frames): ``cam0`` in the bag is an optical frame. Stamps are the headers' (``header.stamp_ns`` as
``builtin_interfaces/Time`` seconds + nanoseconds); each message is written at the time it was recorded.
Only estimated poses (``tracking``, ``recognised``, as ``artrack export --format tum``) are written:
a lost or predicted pose has no measurement of its frame. Other messages (statistics, detections) have no
ROS form here and are counted by key.

ROS 2 topic names are made of letters, digits and ``_`` tokens that do not start with a digit:
``ros_topic`` spells a key so (``pose/cam0/marker/3`` -> ``/pose/cam0/marker_3``).
"""

from __future__ import annotations

import re
from collections import Counter
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from protocol.maps import PointCloud
from protocol.message import Header, Message
from protocol.mocap import Points3D
from protocol.poses import GroundTruth, Pose, RigidBodies
from protocol.sensors import CameraInfo, Image
from protocol.spatial import RIG_FRAME, WORLD_FRAME, FrameTransform, StaticTransforms, Transform
from services.convert import in_tree
from services.geometry.transform_tree import TransformTree
from services.recorder.export import ESTIMATED
from services.recorder.reading import Damage, Scan
from services.recorder.writing import RECORDING_METADATA

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
"""The standard ROS 2 (Jazzy) message types."""
BAG_VERSION: Literal[9] = 9
_T = TYPESTORE.types
_DEFAULT_TIME = QosTime(sec=0, nsec=0)
TF_STATIC_QOS = Qos(QosHistory.KEEP_LAST, 1, QosReliability.RELIABLE, QosDurability.TRANSIENT_LOCAL, _DEFAULT_TIME,
                    _DEFAULT_TIME, QosLiveliness.AUTOMATIC, _DEFAULT_TIME, False)
"""What tf2's static broadcaster offers on ``/tf_static``: a late subscriber still gets the transforms."""
_FIELD: Any = _T["sensor_msgs/msg/PointField"]
"""``sensor_msgs/msg/PointField``, with its datatype constants (``FLOAT32``, ``UINT32``)."""


def ros_time(stamp_ns: int) -> Any:
    """``builtin_interfaces/msg/Time`` of an int nanosecond stamp: whole seconds and the nanoseconds left."""
    return _T["builtin_interfaces/msg/Time"](sec=stamp_ns // 1_000_000_000, nanosec=stamp_ns % 1_000_000_000)


def ros_header(header: Header) -> Any:
    """``std_msgs/msg/Header`` of an artrack header: its stamp and frame id (ROS headers have no sequence)."""
    return _T["std_msgs/msg/Header"](stamp=ros_time(header.stamp_ns), frame_id=header.frame_id)


def ros_topic(key: str) -> str:
    """The ROS 2 topic of ``key`` (relative to the rig prefix): ``/`` + its segments, a camera's ``image``
    as ``image_raw``, characters ROS refuses (``-``, ``.``) as ``_``, and a segment that starts with a digit
    joined to the one before by ``_`` (``marker/3`` -> ``marker_3``; ROS tokens may not start with one), or
    prefixed with ``n`` when it is the first."""
    segments = [re.sub(r"_+", "_", re.sub(r"[^A-Za-z0-9_]", "_", s)) for s in key.split("/")]
    if len(segments) == 2 and segments[1] == "image":
        segments[1] = "image_raw"
    tokens: list[str] = []
    for segment in segments:
        if tokens and segment[:1].isdigit():
            tokens[-1] = f"{tokens[-1]}_{segment}"
        else:
            tokens.append(f"n{segment}" if segment[:1].isdigit() else segment)
    return "/" + "/".join(token.strip("_") or "_" for token in tokens)


def image_message(image: Image) -> Any:
    """``sensor_msgs/msg/Image`` of an artrack image: the same pixels row by row (``step`` = width x pixel
    bytes), the encoding by its ROS name (``mono8``, ``mono16``, ``bgr8``, ``bgra8``), little-endian."""
    data = np.ascontiguousarray(image.data, dtype=image.data.dtype.newbyteorder("<"))
    return _T["sensor_msgs/msg/Image"](header=ros_header(image.header), height=image.height, width=image.width,
                                       encoding=image.encoding, is_bigendian=0, step=data.strides[0],
                                       data=data.reshape(-1).view(np.uint8))


def camera_info_message(info: CameraInfo) -> Any:
    """``sensor_msgs/msg/CameraInfo``: size, distortion model and ``d``, ``k`` (3x3), ``r`` (3x3) and ``p`` (3x4,
    ``[K | 0]`` when the artrack message has none), row-major, pixels; binning and region of interest."""
    p = info.p if info.p is not None else (*info.k[0:3], 0.0, *info.k[3:6], 0.0, *info.k[6:9], 0.0)
    roi = info.roi
    return _T["sensor_msgs/msg/CameraInfo"](
        header=ros_header(info.header), height=info.height, width=info.width, distortion_model=info.distortion_model,
        d=np.array(info.d, dtype=np.float64), k=np.array(info.k, dtype=np.float64),
        r=np.array(info.r, dtype=np.float64), p=np.array(p, dtype=np.float64), binning_x=info.binning_x,
        binning_y=info.binning_y, roi=_T["sensor_msgs/msg/RegionOfInterest"](
            x_offset=roi.x_offset, y_offset=roi.y_offset, height=roi.height, width=roi.width,
            do_rectify=roi.do_rectify))


def _pose(transform: Transform) -> Any:
    (tx, ty, tz), (qx, qy, qz, qw) = transform.translation, transform.rotation
    return _T["geometry_msgs/msg/Pose"](position=_T["geometry_msgs/msg/Point"](x=tx, y=ty, z=tz),
                                        orientation=_T["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw))


def pose_message(pose: Pose) -> Any:
    """``geometry_msgs/msg/PoseStamped`` of ``T_<frame_id>_<child_frame_id>``: the child's origin (m) and
    orientation (unit quaternion x, y, z, w) in the header's frame."""
    return _T["geometry_msgs/msg/PoseStamped"](header=ros_header(pose.header), pose=_pose(pose.transform))


def transform_message(stamp_ns: int, parent: str, child: str, transform: Transform) -> Any:
    """``geometry_msgs/msg/TransformStamped`` of ``T_parent_child`` (translation m, quaternion x, y, z, w)."""
    (tx, ty, tz), (qx, qy, qz, qw) = transform.translation, transform.rotation
    return _T["geometry_msgs/msg/TransformStamped"](
        header=_T["std_msgs/msg/Header"](stamp=ros_time(stamp_ns), frame_id=parent), child_frame_id=child,
        transform=_T["geometry_msgs/msg/Transform"](translation=_T["geometry_msgs/msg/Vector3"](x=tx, y=ty, z=tz),
                                                    rotation=_T["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz,
                                                                                                w=qw)))


def tf_message(transforms: Iterable[Any]) -> Any:
    """``tf2_msgs/msg/TFMessage`` of ``TransformStamped`` messages."""
    return _T["tf2_msgs/msg/TFMessage"](transforms=list(transforms))


def tf_edges(stamp_ns: int, edges: Iterable[FrameTransform]) -> Any:
    """``tf2_msgs/msg/TFMessage`` of ``T_parent_child`` edges, each stamped ``stamp_ns``."""
    return tf_message(transform_message(stamp_ns, edge.parent_frame, edge.child_frame, edge.transform)
                      for edge in edges)


def pose_edge(pose: Pose) -> list[FrameTransform]:
    """A pose as ``/tf`` has it: one transform, ``header.frame_id`` the parent, ``child_frame_id`` the child."""
    return [FrameTransform(parent_frame=pose.header.frame_id, child_frame=pose.child_frame_id,
                           transform=pose.transform)]


def camera_placement(info: CameraInfo) -> list[FrameTransform]:
    """The camera's place in its rig, ``T_rig_camera`` (parent ``rig``, child the camera's optical frame), what a
    ``sensor_msgs/msg/CameraInfo`` cannot say, under ``world -> rig`` (the identity: for a tracker a fixed
    rig's frame is the world its bodies and points are in)."""
    return [FrameTransform(parent_frame=WORLD_FRAME, child_frame=RIG_FRAME, transform=Transform()),
            FrameTransform(parent_frame=RIG_FRAME, child_frame=info.header.frame_id, transform=info.T_rig_camera)]


def ground_truth_message(truth: GroundTruth) -> Any:
    """The exact transforms of one frame (``T_parent_child`` each) under the frame's stamp."""
    return tf_edges(truth.header.stamp_ns, truth.transforms)


def body_edges(bodies: RigidBodies) -> list[FrameTransform]:
    """The estimated bodies (``T_world_body``, child ``body/<name>``), as ``/tf`` has them."""
    return [FrameTransform(parent_frame=bodies.header.frame_id, child_frame=f"body/{body.name}",
                           transform=body.transform) for body in bodies.bodies if body.state in ESTIMATED]


def point_cloud2(header: Header, points: np.ndarray, colors: np.ndarray | None = None) -> Any:
    """``sensor_msgs/msg/PointCloud2`` of ``points`` (N, 3) metres in ``header.frame_id``: one unordered row
    (height 1, width N) of float32 ``x``, ``y``, ``z``, and ``rgb`` (uint32 0x00RRGGBB, as PCL packs it) when
    ``colors`` ((N, 3) uint8 BGR) is given."""
    names = ["x", "y", "z"] + (["rgb"] if colors is not None else [])
    layout = np.dtype({"names": names, "formats": ["<f4"] * 3 + (["<u4"] if colors is not None else [])})
    table = np.zeros(len(points), dtype=layout)
    for axis, name in enumerate("xyz"):
        table[name] = points[:, axis]
    if colors is not None:
        bgr = colors.astype(np.uint32)
        table["rgb"] = (bgr[:, 2] << 16) | (bgr[:, 1] << 8) | bgr[:, 0]
    fields = [_FIELD(name=name, offset=4 * index,  # every field 4 bytes, packed
                     datatype=_FIELD.UINT32 if name == "rgb" else _FIELD.FLOAT32, count=1)
              for index, name in enumerate(names)]
    return _T["sensor_msgs/msg/PointCloud2"](
        header=ros_header(header), height=1, width=len(points), fields=fields, is_bigendian=False,
        point_step=layout.itemsize, row_step=layout.itemsize * len(points), data=table.view(np.uint8),
        is_dense=bool(np.isfinite(points).all()))


def points_message(points: Points3D) -> Any:
    """A rig's triangulated points (``world``) as ``sensor_msgs/msg/PointCloud2`` (``point_cloud2``)."""
    return point_cloud2(points.header, points.points)


def map_message(cloud: PointCloud) -> Any:
    """Map points as ``sensor_msgs/msg/PointCloud2``, coloured when the map has colours (``point_cloud2``)."""
    return point_cloud2(cloud.header, cloud.points, cloud.colors if len(cloud.colors) else None)


Conversion = Callable[[Any], Any]
CONVERSIONS: dict[type[Message], tuple[str, Conversion]] = {
    Image: ("sensor_msgs/msg/Image", image_message),
    CameraInfo: ("sensor_msgs/msg/CameraInfo", camera_info_message),
    Pose: ("geometry_msgs/msg/PoseStamped", pose_message),
    GroundTruth: ("tf2_msgs/msg/TFMessage", ground_truth_message),
    Points3D: ("sensor_msgs/msg/PointCloud2", points_message),
    PointCloud: ("sensor_msgs/msg/PointCloud2", map_message),
}
"""Messages written on their key's own topic: their ROS type and conversion."""


@dataclass
class RosbagExport:
    """What ``export_rosbag`` wrote: messages by ROS topic, keys with no ROS form (message counts), messages
    that did not decode, and the damage that ended the recording (None: intact)."""

    topics: Counter[str] = field(default_factory=Counter)
    types: dict[str, str] = field(default_factory=dict)
    left_out: Counter[str] = field(default_factory=Counter)
    undecodable: int = 0
    damage: Damage | None = None


class _Bag:
    """A bag being written: a connection per topic, made the first time the topic is written."""

    def __init__(self, writer: Writer, done: RosbagExport):
        self.writer = writer
        self.done = done
        self.connections: dict[str, Any] = {}
        self.placed: set[str] = set()
        """Cameras whose ``T_rig_camera`` is on ``/tf_static`` already."""
        self.tree = TransformTree()
        """``/tf`` and ``/tf_static`` together: one parent per frame."""

    def write_tf(self, topic: str, edges: list[FrameTransform], stamp_ns: int, time_ns: int) -> None:
        """``edges`` on ``topic`` (``/tf`` or ``/tf_static``) as they join the bag's tree (``in_tree``)."""
        if edges:
            self.write(topic, "tf2_msgs/msg/TFMessage", tf_edges(stamp_ns, in_tree(self.tree, edges)), time_ns)

    def write(self, topic: str, msgtype: str, message: Any, time_ns: int) -> None:
        connection = self.connections.get(topic)
        if connection is None:
            qos = [TF_STATIC_QOS] if topic == "/tf_static" else []
            connection = self.writer.add_connection(topic, msgtype, typestore=TYPESTORE, offered_qos_profiles=qos)
            self.connections[topic] = connection
            self.done.types[topic] = msgtype
        self.writer.write(connection, time_ns, TYPESTORE.serialize_cdr(message, msgtype))
        self.done.topics[topic] += 1


def export_rosbag(path: Path | str, out: Path | str) -> RosbagExport:
    """Write every message of the recording ``path`` that has a ROS form into a new ROS 2 bag, folder ``out``
    (``out/<name>.mcap`` + ``metadata.yaml``; it must not exist), each at its recorded time. A damaged
    recording gives its intact part (``damage`` says where it ended)."""
    scan = Scan(path)
    done = RosbagExport()
    with Writer(out, version=BAG_VERSION, storage_plugin=StoragePlugin.MCAP) as writer:
        bag = _Bag(writer, done)
        for recorded, message in scan.decoded():
            recording = scan.metadata.get(RECORDING_METADATA, {})
            prefix = f"{recording['namespace']}/{recording['rig']}/" if "rig" in recording else ""
            key = recorded.channel.topic.removeprefix(prefix)
            if not _write(bag, key, message, recorded.message.log_time):
                done.left_out[key] += 1
    done.undecodable, done.damage = scan.undecodable, scan.damage
    return done


def _write(bag: _Bag, key: str, message: Message, time_ns: int) -> bool:
    """Write ``message``, recorded on ``key`` at ``time_ns``, as its ROS forms; False when it has none."""
    if isinstance(message, Pose):
        if message.state in ESTIMATED:
            bag.write(ros_topic(key), "geometry_msgs/msg/PoseStamped", pose_message(message), time_ns)
            bag.write_tf("/tf", pose_edge(message), message.header.stamp_ns, time_ns)
        return True
    if isinstance(message, RigidBodies):
        bag.write_tf("/tf", body_edges(message), message.header.stamp_ns, time_ns)
        return True
    if isinstance(message, StaticTransforms):
        bag.write_tf("/tf_static", list(message.transforms), message.header.stamp_ns, time_ns)
        return True
    if isinstance(message, CameraInfo) and message.header.frame_id not in bag.placed:
        bag.placed.add(message.header.frame_id)
        bag.write_tf("/tf_static", camera_placement(message), message.header.stamp_ns, time_ns)
    conversion = CONVERSIONS.get(type(message))
    if conversion is None:
        return False
    msgtype, convert = conversion
    bag.write(ros_topic(key), msgtype, convert(message), time_ns)
    return True
