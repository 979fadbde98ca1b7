"""What the benchmark sends (senders, in the bench process) and how the sink reads it (readers).

Three kinds of traffic:

* ``typed`` images: for every message a ``protocol.Image`` is built around the numpy frame
  and put through ``services.bus.pubsub.Publisher``, which encodes it; the sink runs
  ``protocol.decode`` on ``services.bus.shm.received_bytes`` and gets the pixels as a read-only
  numpy view.
* ``raw`` images: the same frame as plain bytes, joined behind a zero-padded prefix that makes
  the payload exactly as long as the typed one (one copy of the pixels, as ``encode`` makes),
  put through ``services.bus.pubsub.RawPublisher`` (what ``Publisher`` puts its encoded
  bytes through); the sink does ``services.bus.shm.received_bytes`` (what an ``Inbox`` does) and
  ``np.frombuffer``.
* poses: a ``protocol.Pose`` (JSON codec) built and put through ``Publisher``, decoded by the sink.

Both kinds of image go through ``RawPublisher.put``, so both are written into the publisher's
shared-memory pool (``services.bus.shm``), and both are read back the same way.

Every message carries its send time, ``time.time_ns()`` (CLOCK_REALTIME, shared by the
processes of one host) taken before the message is built: the typed ones in
``header.stamp_ns``, the raw ones in the prefix's first 8 bytes. A reader returns that stamp
after doing its decoding work, so latency covers building, encoding, transport and decoding.
"""

from __future__ import annotations

import math
import struct
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
import zenoh

from protocol import Header, Image, Pose, PoseQuality, Transform, decode, encode
from services.bus.pubsub import Publisher, RawPublisher, Role
from services.bus.shm import received_bytes

STAMP = struct.Struct("<q")
FRAME_ID = "cam0"


class Sender(Protocol):
    """One publisher of the benchmark: ``send`` puts one message stamped with the current time."""

    def send(self, seq: int) -> None: ...

    def matched(self) -> bool: ...

    def close(self) -> None: ...


SenderFactory = Callable[[zenoh.Session, str, Role], Sender]


@dataclass(frozen=True)
class ImageCase:
    """One image size: ``shape`` (H, W) or (H, W, 3), uint8, with its ``protocol.Image`` encoding."""

    shape: tuple[int, ...]
    encoding: str

    @property
    def name(self) -> str:
        return f"image_{self.shape[1]}x{self.shape[0]}_{self.encoding}"

    def frame(self) -> np.ndarray:
        """Random pixels (incompressible, though nothing on the path compresses)."""
        return np.random.default_rng(0).integers(0, 256, self.shape, dtype=np.uint8)

    def message(self, frame: np.ndarray, seq: int) -> Image:
        header = Header(stamp_ns=time.time_ns(), frame_id=FRAME_ID, seq=seq)
        return Image(header=header, encoding=self.encoding, data=frame)

    def typed_payload_bytes(self, frame: np.ndarray) -> int:
        return len(encode(self.message(frame, 0)))


class TypedImageSender:
    """Builds an ``Image`` around the frame and puts it through ``Publisher`` (which encodes it)."""

    def __init__(self, session: zenoh.Session, key: str, role: Role, case: ImageCase, frame: np.ndarray):
        self._case, self._frame = case, frame
        self._publisher = Publisher(session, key, Image, role)

    def send(self, seq: int) -> None:
        self._publisher.put(self._case.message(self._frame, seq))

    def matched(self) -> bool:
        return self._publisher.matched()

    def close(self) -> None:
        self._publisher.close()


class RawImageSender:
    """Puts stamp + zero padding + the frame's bytes, joined into one ``bytes``, through ``RawPublisher``
    (the same QoS and counting as ``Publisher``, which hands its encoded payloads to one)."""

    def __init__(self, session: zenoh.Session, key: str, role: Role, frame: np.ndarray, payload_bytes: int):
        self._padding = bytes(payload_bytes - frame.nbytes - STAMP.size)
        self._pixels = frame.data.cast("B")
        self._publisher = RawPublisher(session, key, role, zenoh.Encoding.APPLICATION_OCTET_STREAM)

    def send(self, seq: int) -> None:
        self._publisher.put(b"".join((STAMP.pack(time.time_ns()), self._padding, self._pixels)))

    def matched(self) -> bool:
        return self._publisher.matched()

    def close(self) -> None:
        self._publisher.close()


class PoseSender:
    """Builds a marker ``Pose`` (transform, quality) per message and puts it through ``Publisher``."""

    def __init__(self, session: zenoh.Session, key: str, role: Role):
        self._publisher = Publisher(session, key, Pose, role)

    def send(self, seq: int) -> None:
        self._publisher.put(pose_message(seq))

    def matched(self) -> bool:
        return self._publisher.matched()

    def close(self) -> None:
        self._publisher.close()


def pose_message(seq: int) -> Pose:
    """A typical marker pose, stamped now."""
    return Pose(
        header=Header(stamp_ns=time.time_ns(), frame_id=FRAME_ID, seq=seq),
        child_frame_id="marker/7",
        transform=Transform(translation=(0.12, -0.05, 0.8), rotation=(0.0, 0.0, 0.38268343, 0.92387953)),
        quality=PoseQuality(reprojection_rms_px=0.4, inliers=4),
    )


def typed_reader_spec() -> dict[str, Any]:
    """The sink decodes with ``protocol.decode`` (images and poses alike)."""
    return {"kind": "typed"}


def raw_reader_spec(shape: tuple[int, ...], payload_bytes: int) -> dict[str, Any]:
    """The sink views the pixels after the prefix with ``np.frombuffer``."""
    return {"kind": "raw", "shape": list(shape), "offset": payload_bytes - math.prod(shape)}


def reader(spec: dict[str, Any]) -> Callable[[zenoh.Sample], int]:
    """The sink-side work for ``spec``: take the payload, decode or view it, return the send stamp."""
    if spec["kind"] == "typed":
        return lambda sample: decode(received_bytes(sample.payload)).header.stamp_ns
    shape, offset = tuple(spec["shape"]), spec["offset"]
    count = math.prod(shape)

    def read_raw(sample: zenoh.Sample) -> int:
        payload = received_bytes(sample.payload)
        np.frombuffer(payload, np.uint8, count, offset).reshape(shape)  # the view a raw user works with
        return STAMP.unpack_from(payload)[0]

    return read_raw
