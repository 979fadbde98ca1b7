"""A ROS 2 bag as a frame source (``rosbag2:DIR``), read without a ROS install (``rosbags``).

Image topics are those of type ``sensor_msgs/msg/Image`` (encodings ``mono8``, ``mono16``, ``bgr8``,
``rgb8``, ``bgra8``, ``rgba8``; colour ones come out BGR as OpenCV holds them) or
``sensor_msgs/msg/CompressedImage`` (decoded by OpenCV). ``rosbag2:DIR?topic=/cam0/image_raw`` takes the
named topic (repeat ``topic=`` with ``&`` for several); without, every image topic of the bag is a camera.
A camera is named after its topic's namespace (``/cam0/image_raw`` -> ``cam0``, ``/stereo/left/image_raw``
-> ``stereo_left``; a topic with none -> ``cam0``), and several cameras go in step: an instant is a stamp
every camera has an image at (``header.stamp``); images without a partner are left out.

A frame's time is its header stamp (int ns). A camera's calibration is the first
``sensor_msgs/msg/CameraInfo`` on the ``camera_info`` topic beside its images (``/cam0/camera_info``),
``plumb_bob`` distortion; its frame is the ROS optical frame, which is OpenCV's camera frame, so K and the
distortion are taken as they are. A CameraInfo whose K is zero (an uncalibrated driver's) is none. A camera's
place in its rig, ``T_rig_camera``, is the ``/tf_static`` transform from ``rig`` to the CameraInfo's frame
(what ``artrack export --format rosbag2`` writes), the identity without one. Pure: no bus here.
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Any
from urllib.parse import parse_qs

import cv2
import numpy as np

from services.geometry.camera import CameraModel
from services.geometry.se3 import from_quaternion_translation

IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
CAMERA_INFO_TYPE = "sensor_msgs/msg/CameraInfo"
TF_STATIC, TF_TYPE = "/tf_static", "tf2_msgs/msg/TFMessage"
RIG_FRAME = "rig"
"""The frame cameras are placed in on ``/tf_static`` (artrack's rig frame)."""
_LAYOUTS = {"mono8": (np.uint8, 1), "8UC1": (np.uint8, 1), "mono16": (np.uint16, 1), "16UC1": (np.uint16, 1),
            "bgr8": (np.uint8, 3), "8UC3": (np.uint8, 3), "rgb8": (np.uint8, 3), "bgra8": (np.uint8, 4),
            "8UC4": (np.uint8, 4), "rgba8": (np.uint8, 4)}
_TO_BGR = {"rgb8": cv2.COLOR_RGB2BGR, "rgba8": cv2.COLOR_RGBA2BGRA}


@cache
def typestore() -> Any:
    """The ROS 2 Jazzy message types (``rosbags``), built on first use: importing ``rosbags`` and building them takes
    a few tenths of a second that a capture of any other source should not pay."""
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)


def reader(folder: Path) -> Any:
    """A ``rosbags`` reader of the bag in ``folder`` (imported on first use, as ``typestore``)."""
    from rosbags.rosbag2 import Reader

    return Reader(folder)


class BagError(ValueError):
    """A bag that cannot be a source: missing, not a bag, no image topic, an unknown topic asked for."""


def split_uri(rest: str) -> tuple[Path, tuple[str, ...]]:
    """``(folder, topics)`` of what follows ``rosbag2:``: ``DIR`` or ``DIR?topic=/a&topic=/b``."""
    folder, _, query = rest.partition("?")
    return Path(folder).expanduser(), tuple(parse_qs(query).get("topic", []))


def camera_name(topic: str) -> str:
    """The camera of an image topic: its namespace's tokens joined by ``_`` (``cam0`` when it has none)."""
    tokens = [t for t in topic.split("/")[:-1] if t]
    return re.sub(r"[^A-Za-z0-9_.\-]", "_", "_".join(tokens)) or "cam0"


def image_array(message: Any) -> np.ndarray:
    """(H, W) or (H, W, 3|4) uint8/uint16 image of a ``sensor_msgs/msg/Image`` (rows read by ``step``, the
    byte order by ``is_bigendian``, RGB turned BGR) or ``CompressedImage`` (cv2.imdecode, unchanged depth);
    ValueError for an encoding it cannot hold."""
    if not hasattr(message, "encoding"):
        image = cv2.imdecode(np.asarray(message.data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
        if image is None:
            raise ValueError(f"compressed image ({message.format or 'unknown format'}) does not decode")
        return image
    layout = _LAYOUTS.get(message.encoding)
    if layout is None:
        raise ValueError(f"image encoding {message.encoding!r} is not one artrack reads ({', '.join(_LAYOUTS)})")
    dtype, channels = np.dtype(layout[0]).newbyteorder(">" if message.is_bigendian else "<"), layout[1]
    row_bytes = message.width * channels * dtype.itemsize
    rows = np.asarray(message.data, dtype=np.uint8).reshape(message.height, message.step)[:, :row_bytes]
    image = np.ascontiguousarray(rows).view(dtype).astype(dtype.newbyteorder("="))
    image = image.reshape(message.height, message.width, channels) if channels > 1 else \
        image.reshape(message.height, message.width)
    return cv2.cvtColor(image, _TO_BGR[message.encoding]) if message.encoding in _TO_BGR else image


def camera_from_info(message: Any, name: str, T_rig_camera: np.ndarray | None = None) -> CameraModel | None:
    """CameraModel ``name`` of a ``sensor_msgs/msg/CameraInfo`` (K row-major, plumb_bob ``d`` padded to 5) placed
    at ``T_rig_camera`` ((4, 4), default the identity); None when K is zero (no calibration); ValueError for
    another distortion model."""
    K = np.asarray(message.k, dtype=np.float64).reshape(3, 3)
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        return None
    d = np.asarray(message.d, dtype=np.float64)
    if message.distortion_model not in ("plumb_bob", "") or len(d) > 5:
        raise ValueError(f"camera {name}: distortion model {message.distortion_model!r} with {len(d)} coefficients "
                         "is not supported (plumb_bob only)")
    return CameraModel(name=name, width=int(message.width), height=int(message.height), K=K,
                       dist=np.pad(d, (0, 5 - len(d))),
                       T_rig_camera=np.eye(4) if T_rig_camera is None else T_rig_camera)


def placements(message: Any) -> dict[str, np.ndarray]:
    """``{child frame: T_rig_child (4, 4)}`` of the transforms of a ``tf2_msgs/msg/TFMessage`` whose parent is
    ``rig``."""
    found = {}
    for edge in message.transforms:
        if edge.header.frame_id == RIG_FRAME:
            t, q = edge.transform.translation, edge.transform.rotation
            found[edge.child_frame_id] = from_quaternion_translation(np.array([q.x, q.y, q.z, q.w]),
                                                                     np.array([t.x, t.y, t.z]))
    return found


def stamp_ns(message: Any) -> int:
    """A message's header stamp in int nanoseconds."""
    return int(message.header.stamp.sec) * 1_000_000_000 + int(message.header.stamp.nanosec)


@dataclass(frozen=True)
class Frame:
    """One instant of a bag: its stamp (ns) and an image per camera name."""

    time_ns: int
    images: dict[str, np.ndarray]


class Bag:
    """An opened ROS 2 bag's image topics, as cameras; ``topics`` the ones asked for (default: all)."""

    def __init__(self, folder: Path, topics: tuple[str, ...] = ()):
        if not folder.is_dir():
            raise BagError("no such folder")
        if not (folder / "metadata.yaml").is_file():
            raise BagError("not a ROS 2 bag (no metadata.yaml)")
        self.folder = folder
        try:
            with reader(folder) as bag:
                self.types = {c.topic: c.msgtype for c in bag.connections}
                self.counts = {topic: info.msgcount for topic, info in bag.topics.items()}
        except Exception as exc:  # rosbags raises its own errors and yaml's for a damaged metadata file
            raise BagError(f"cannot read the bag ({exc})") from exc
        images = sorted(topic for topic, msgtype in self.types.items() if msgtype in IMAGE_TYPES)
        if not images:
            listed = ", ".join(f"{t} ({m})" for t, m in sorted(self.types.items())) or "none"
            raise BagError(f"no image topic ({' or '.join(IMAGE_TYPES)}) in the bag (topics: {listed})")
        unknown = [topic for topic in topics if topic not in images]
        if unknown:
            raise BagError(f"{unknown[0]} is not an image topic of the bag (image topics: "
                           f"{', '.join(images)})")
        self.topics = topics or tuple(images)
        names = [camera_name(topic) for topic in self.topics]
        if len(set(names)) < len(names):
            names = [re.sub(r"[^A-Za-z0-9_]", "_", topic.strip("/")) for topic in self.topics]
        self.cameras = dict(zip(self.topics, names, strict=True))

    def info_topic(self, topic: str) -> str | None:
        """The ``camera_info`` topic beside image ``topic``, when the bag has one."""
        beside = topic.rsplit("/", 1)[0] + "/camera_info"
        return beside if self.types.get(beside) == CAMERA_INFO_TYPE else None

    def calibration(self) -> dict[str, CameraModel]:
        """Each camera's model from the first calibrated CameraInfo beside its images (cameras without one left
        out), placed in the rig by the ``/tf_static`` transform from ``rig`` to its frame when the bag has one."""
        wanted = {info: self.cameras[topic] for topic in self.topics if (info := self.info_topic(topic))}
        infos: dict[str, Any] = {}
        for topic, message in self._messages(set(wanted)):
            if wanted[topic] not in infos and np.asarray(message.k).any():
                infos[wanted[topic]] = message
            if len(infos) == len(wanted):
                break
        placed: dict[str, np.ndarray] = {}
        if self.types.get(TF_STATIC) == TF_TYPE:
            for _, message in self._messages({TF_STATIC}):
                placed.update(placements(message))
        found = {name: camera_from_info(info, name, placed.get(info.header.frame_id)) for name, info in infos.items()}
        return {name: camera for name, camera in found.items() if camera is not None}

    def first_sizes(self) -> list[tuple[int, int] | None]:
        """``(width, height)`` of each camera's first image, in camera order (None when it does not read)."""
        sizes: dict[str, tuple[int, int] | None] = {}
        for topic, message in self._messages(set(self.topics)):
            if topic not in sizes:
                try:
                    image = image_array(message)
                    sizes[topic] = (image.shape[1], image.shape[0])
                except ValueError:
                    sizes[topic] = None
            if len(sizes) == len(self.topics):
                break
        return [sizes.get(topic) for topic in self.topics]

    def frame_count(self) -> int:
        """Images of the camera with the fewest (the instants in step can be fewer)."""
        return min(self.counts.get(topic, 0) for topic in self.topics)

    def frames(self) -> Iterator[Frame | tuple[int, str]]:
        """Instants in step, in bag order; an image that does not convert as ``(stamp, reason)``."""
        pending: dict[int, dict[str, np.ndarray]] = {}
        for topic, message in self._messages(set(self.topics)):
            stamp = stamp_ns(message)
            try:
                image = image_array(message)
            except ValueError as exc:
                yield stamp, f"{topic}: {exc}"
                continue
            images = pending.setdefault(stamp, {})
            images[self.cameras[topic]] = image
            if len(images) == len(self.topics):
                del pending[stamp]
                for older in [s for s in pending if s < stamp]:  # their partners will not come any more
                    del pending[older]
                yield Frame(stamp, images)

    def _messages(self, topics: set[str]) -> Iterator[tuple[str, Any]]:
        """(topic, deserialized message) of the messages on ``topics``, in bag order."""
        if not topics:
            return
        with reader(self.folder) as bag:
            connections = [c for c in bag.connections if c.topic in topics]
            for connection, _, data in bag.messages(connections=connections):
                yield connection.topic, typestore().deserialize_cdr(data, connection.msgtype)
