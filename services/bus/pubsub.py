"""Typed publishing and subscribing on top of the wire codec.

Streams have a role that sets their Zenoh quality of service and their queueing:

* ``FRAME`` (images): priority DATA, congestion DROP. Subscribers keep only the newest
  ``depth`` payloads (latest-wins); every replaced payload is counted as dropped.
* ``RESULT`` (poses, detections): priority DATA_HIGH, so frames can never stall them;
  congestion BLOCK, so the publisher waits rather than drop. Subscribers queue up to
  ``depth`` (default 10 000) in order; should a consumer fall that far behind, the oldest
  are dropped, counted and logged, never silently. Not express: Zenoh then sends a frame's
  poses that are ready together in one batch, so each subscriber wakes once per frame rather
  than once per pose: pose throughput is higher and client apps slow the marker pipeline less
  (the batched figures: ``make bench BENCH="routing apps"``, docs/benchmarks.md).
* ``STATUS`` (stats, error reports): priority DATA_LOW, congestion DROP.
* ``END`` (a node's end of stream, and its last statistics just before it): priority DATA_LOW
  as status, congestion BLOCK, so the two are never dropped and arrive in that order.

A lossless run (a finite source under flow control, ``services.runtime.flow``) publishes frames
with congestion BLOCK instead, and its subscribers queue every frame: the source's credits bound
how many can be waiting. A frame inbox counts the frames that never reached it by the gaps in
their ``header.seq`` (``SeqGaps``), as ``missing``.

Payloads are decoded on the consumer's thread, not in Zenoh's callback, so the callback
only copies bytes into a bounded queue. A payload that fails to decode is counted, handed
to ``on_decode_error`` and skipped.
"""

from __future__ import annotations

import functools
import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from enum import StrEnum
from typing import Generic, TypedDict, TypeVar, cast

import zenoh

from protocol.codec import DecodeError, decode, encode, media_type, peek
from protocol.message import Message
from services.bus.local import LocalBus, Payload, deliver
from services.bus.shm import ShmPayloads, received_bytes
from services.bus.stats import SeqGaps, StreamCounter

log = logging.getLogger(__name__)

M = TypeVar("M", bound=Message)


class Role(StrEnum):
    FRAME = "frame"
    RESULT = "result"
    STATUS = "status"
    END = "end"


class _Qos(TypedDict):
    priority: zenoh.Priority
    congestion_control: zenoh.CongestionControl


_QOS: dict[Role, _Qos] = {
    Role.FRAME: {"priority": zenoh.Priority.DATA, "congestion_control": zenoh.CongestionControl.DROP},
    Role.RESULT: {"priority": zenoh.Priority.DATA_HIGH, "congestion_control": zenoh.CongestionControl.BLOCK},
    Role.STATUS: {"priority": zenoh.Priority.DATA_LOW, "congestion_control": zenoh.CongestionControl.DROP},
    Role.END: {"priority": zenoh.Priority.DATA_LOW, "congestion_control": zenoh.CongestionControl.BLOCK},
}

DEFAULT_DEPTH = {Role.FRAME: 1, Role.RESULT: 10_000, Role.STATUS: 100, Role.END: 100}


class RawPublisher:
    """Publishes payloads that are already encoded (a recording's bytes, untouched) on one key.

    ``role`` sets the QoS (with ``lossless``, frames block rather than drop); ``encoding`` is the
    Zenoh encoding to announce. With ``local`` (the process's ``LocalBus``), the process's own
    subscribers get the payload from here and the bus only while another session subscribes.
    Payloads of ``services.bus.shm.THRESHOLD`` bytes or more go onto the bus from this publisher's
    shared-memory pool.
    """

    def __init__(self, session: zenoh.Session, key: str, role: Role, encoding: zenoh.Encoding,
                 counter: StreamCounter | None = None, lossless: bool = False, local: LocalBus | None = None):
        self.key = key
        self.role = role
        self.counter = counter or StreamCounter(key, "out")
        self.local = local
        qos = _QOS[role]
        if lossless and role is Role.FRAME:
            qos = {**qos, "congestion_control": zenoh.CongestionControl.BLOCK}
        destination = zenoh.Locality.ANY if local is None else zenoh.Locality.REMOTE
        self._publisher = session.declare_publisher(key, encoding=encoding, allowed_destination=destination, **qos)
        self._shm = ShmPayloads()
        self._matched = False
        self._listener = self._publisher.declare_matching_listener(self._on_matching)
        self._matched = self._publisher.matching_status.matching  # type: ignore[attr-defined]  # a MatchingStatus

    def _on_matching(self, status: zenoh.MatchingStatus) -> None:
        self._matched = status.matching

    def put(self, payload: bytes) -> None:
        if self.local is None:
            self.send(payload)
        else:
            sinks = self.local.sinks(self.key)
            for sink in sinks:
                sink.offer(self.key, payload)
            if self.wanted():
                self.local.outbox.send(functools.partial(self.send, payload), defer=bool(sinks))
        self.counter.count(messages=1)

    def wanted(self) -> bool:
        """Whether the bus needs the payload: always without a local bus, else while another session subscribes."""
        return self.local is None or self._matched

    def send(self, payload: bytes) -> None:
        """Put ``payload`` on the bus (uncounted: ``put`` counts)."""
        self._publisher.put(self._shm.payload(payload))

    def matched(self) -> bool:
        """True while at least one subscriber takes this key, in this process or another session. The other
        sessions' are kept by a matching listener: asking Zenoh gives up the GIL, which a busy process may take
        long to give back."""
        return self._matched or (self.local is not None and bool(self.local.sinks(self.key)))

    def close(self) -> None:
        self._listener.undeclare()
        self._publisher.undeclare()


class Publisher(Generic[M]):
    """Publishes messages of one type on one key: by reference to the process's own subscribers (with
    ``local``), encoded once for the bus and for raw taps, only when one of them wants it; the bus's copy
    leaves from ``local``'s outbox."""

    def __init__(self, session: zenoh.Session, key: str, cls: type[M], role: Role,
                 counter: StreamCounter | None = None, lossless: bool = False, local: LocalBus | None = None):
        self.key = key
        self.cls = cls
        self.role = role
        self.raw = RawPublisher(session, key, role, zenoh.Encoding(media_type(cls)).with_schema(cls.SCHEMA), counter,
                                lossless, local)
        self.counter = self.raw.counter

    def put(self, message: M) -> None:
        if not isinstance(message, self.cls):
            raise TypeError(f"{self.key} carries {self.cls.__name__}, not {type(message).__name__}")
        encoded: list[bytes] = []

        def once() -> bytes:
            if not encoded:
                encoded.append(encode(message))
            return encoded[0]

        local = self.raw.local
        if local is None:
            self.raw.send(once())
        else:
            sinks = local.sinks(self.key)
            deliver(sinks, self.key, message, once)
            if self.raw.wanted():
                local.outbox.send(lambda: self.raw.send(once()), defer=bool(sinks))
        self.counter.count(messages=1)

    def matched(self) -> bool:
        return self.raw.matched()

    def close(self) -> None:
        self.raw.close()


@dataclass(frozen=True)
class Received(Generic[M]):
    """A decoded message with the key it came on and its arrival time (``time.time_ns()``)."""

    key: str
    message: M
    received_ns: int


def decode_as(payload: bytes, cls: type[M] | None) -> M:
    """``payload`` decoded, and of type ``cls`` unless that is None (DecodeError otherwise)."""
    message = decode(payload)
    if cls is not None and not isinstance(message, cls):
        raise DecodeError(f"expected {cls.SCHEMA} on this key", schema=message.SCHEMA, size=len(payload))
    return cast(M, message)


class Inbox(Generic[M]):
    """Messages arriving on a key expression, queued by role, decoded when taken.

    ``cls`` restricts the inbox to one message type (anything else counts as a decode
    error); ``None`` accepts every artrack message. ``wake`` lets several inboxes share one
    condition so a consumer can wait on all of them at once; ``notify`` is called (on Zenoh's
    thread) after each arrival, for a consumer that waits elsewhere (an asyncio loop). With
    ``local`` (the process's ``LocalBus``), publishers of the same process hand their messages
    over by reference, taken as they are (a node of the same process built them): their Zenoh
    publishers send to other sessions only, so the same message never comes twice.
    """

    wants_bytes = False

    def __init__(self, session: zenoh.Session, key: str, cls: type[M] | None, role: Role, *,
                 depth: int | None = None, counter: StreamCounter | None = None,
                 on_decode_error: Callable[[str, DecodeError], None] | None = None,
                 wake: threading.Condition | None = None, notify: Callable[[], object] | None = None,
                 local: LocalBus | None = None):
        self.key = key
        self.cls = cls
        self.role = role
        self.depth = depth or DEFAULT_DEPTH[role]
        self.counter = counter or StreamCounter(key, "in")
        self.wake = wake or threading.Condition()
        self._on_decode_error = on_decode_error
        self._notify = notify
        self._queue: deque[tuple[str, Payload, int]] = deque()
        self._latest: Received[M] | None = None
        self._warned_at = -1.0
        self._gaps = SeqGaps() if role is Role.FRAME else None
        self._local = local
        self._subscriber = session.declare_subscriber(key, self._on_sample)
        if local is not None:
            local.attach(self)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        self.offer(str(sample.key_expr), received_bytes(sample.payload))

    def offer(self, key: str, payload: Payload) -> None:
        """Queue ``payload`` that arrived on ``key`` (a message from this process, or bytes)."""
        item = (key, payload, time.time_ns())
        missing = 0
        with self.wake:
            if self._gaps is not None and (seq := _seq(item[1])) >= 0:
                missing = self._gaps.note(key, seq)
            dropped = len(self._queue) >= self.depth
            if dropped:
                self._queue.popleft()
            self._queue.append(item)
            self.wake.notify_all()
        self.counter.count(messages=1, dropped=int(dropped), missing=missing, key=key)
        if self._notify is not None:
            self._notify()
        if dropped and self.role is not Role.FRAME and time.monotonic() - self._warned_at > 1.0:
            self._warned_at = time.monotonic()
            log.warning("%s: consumer %d messages behind, dropping the oldest (%d dropped so far)",
                        self.key, self.depth, self.counter.dropped)

    def pending(self) -> int:
        """Payloads waiting to be taken."""
        return len(self._queue)

    def count_tail(self, last_seq: int) -> int:
        """Count as missing the frames after the last one received, up to the source's ``last_seq``
        (frame inboxes only); the number counted."""
        if self._gaps is None:
            return 0
        with self.wake:
            missing = self._gaps.tail(last_seq)
        self.counter.count(missing=missing)
        return missing

    def take(self) -> Received[M] | None:
        """The oldest queued message, decoded; None when the queue is empty.

        Payloads that fail to decode are counted and skipped.
        """
        while True:
            with self.wake:
                if not self._queue:
                    return None
                item = self._queue.popleft()
            if (received := self._decoded(*item)) is not None:
                return received

    def take_newest(self) -> Received[M] | None:
        """The newest queued message, decoded, every older one let go undecoded (a state that each message
        replaces, such as a camera's calibration); None when the queue is empty. A newest payload that fails to
        decode is counted and the one before it taken."""
        with self.wake:
            queued = list(self._queue)
            self._queue.clear()
        for item in reversed(queued):
            if (received := self._decoded(*item)) is not None:
                return received
        return None

    def _decoded(self, key: str, payload: Payload, received_ns: int) -> Received[M] | None:
        """One queued payload decoded (and kept as the latest); None, counted, when it fails to decode."""
        try:
            message = decode_as(payload, self.cls) if isinstance(payload, bytes) else self._check(payload)
        except DecodeError as error:
            self.counter.count(decode_errors=1)
            if self._on_decode_error is not None:
                self._on_decode_error(key, error)
            return None
        self._latest = Received(key, message, received_ns)
        return self._latest

    def _check(self, message: Message) -> M:
        """A message handed over in this process, as it is; DecodeError when it is not of the inbox's type."""
        if self.cls is not None and not isinstance(message, self.cls):
            raise DecodeError(f"expected {self.cls.SCHEMA} on this key", schema=message.SCHEMA)
        return cast(M, message)

    def recv(self, timeout_s: float | None = None) -> Received[M] | None:
        """Wait up to ``timeout_s`` (forever when None) for a message; None on timeout."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        while True:
            received = self.take()
            if received is not None:
                return received
            with self.wake:
                if self._queue:
                    continue
                remaining = None if deadline is None else deadline - time.monotonic()
                if remaining is not None and remaining <= 0:
                    return None
                self.wake.wait(remaining)

    def latest(self) -> Received[M] | None:
        """Drain the queue and return the newest valid message seen so far (kept between calls)."""
        while self.take() is not None:
            pass
        return self._latest

    def close(self) -> None:
        if self._local is not None:
            self._local.detach(self)
        self._subscriber.undeclare()


def _seq(payload: Payload) -> int:
    """The ``header.seq`` of a payload, -1 when it does not peek (its decode error is counted when taken)."""
    if isinstance(payload, Message):
        return payload.header.seq
    try:
        return peek(payload).seq
    except DecodeError:
        return -1


class Listener(Generic[M]):
    """Messages on a key expression handed to ``handler`` as they arrive, decoded on Zenoh's thread.

    For small messages a consumer wants at once (a callback per pose); frames belong in an
    ``Inbox``. Payloads that fail to decode (or are not ``cls``) are counted, handed to
    ``on_decode_error`` and skipped. ``handler`` must not block: it holds up this key's delivery.
    """

    def __init__(self, session: zenoh.Session, key: str, cls: type[M] | None,
                 handler: Callable[[Received[M]], None], *, counter: StreamCounter | None = None,
                 on_decode_error: Callable[[str, DecodeError], None] | None = None):
        self.key = key
        self.counter = counter or StreamCounter(key, "in")
        self._cls = cls
        self._handler = handler
        self._on_decode_error = on_decode_error
        self._subscriber = session.declare_subscriber(key, self._on_sample)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        received_ns = time.time_ns()
        key = str(sample.key_expr)
        try:
            message = decode_as(received_bytes(sample.payload), self._cls)
        except DecodeError as error:
            self.counter.count(decode_errors=1)
            if self._on_decode_error is not None:
                self._on_decode_error(key, error)
            return
        self.counter.count(messages=1)
        self._handler(Received(key, message, received_ns))

    def close(self) -> None:
        self._subscriber.undeclare()
