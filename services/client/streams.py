"""Pose streams a client app reads: decoded on arrival, handed out as ``PoseUpdate``.

A ``Feed`` is one Zenoh subscriber on a pose key expression. It decodes each payload on
Zenoh's thread (poses are a few hundred bytes), counts what it received, dropped and could
not decode, and passes each update to a sink:

* ``PoseStream``: a bounded queue read by a plain ``for`` loop (``queue.SimpleQueue``, whose
  put and waiting get are C code: a few lines of Python per pose instead of a ``Condition``'s
  dozens, which matters when every pose wakes the app's thread);
* ``AsyncPoseStream``: an asyncio queue read by ``async for``;
* a callback (``Client.on_pose``).

Poses are results, never dropped silently: a queue that overflows because the app reads too
slowly drops its oldest update, counts it and logs it once per second.
"""

from __future__ import annotations

import asyncio
import logging
import queue
import threading
import time
from collections.abc import AsyncIterator, Callable, Iterator
from dataclasses import dataclass

import zenoh

from protocol.codec import DecodeError, decode
from protocol.keys import Keys
from protocol.poses import Pose
from protocol.system import Subscription

log = logging.getLogger(__name__)

DEFAULT_DEPTH = 10_000
POLL_S = 0.1
WARN_EVERY_S = 1.0


@dataclass(frozen=True)
class PoseUpdate:
    """One pose as it reached the app.

    ``target`` is the target's name under the rig (``cam0/marker/7``), ``pose`` the message
    (``T_<pose.header.frame_id>_<pose.child_frame_id>``), ``received_ns`` the wall-clock arrival
    time in ns.
    """

    target: str
    pose: Pose
    received_ns: int

    @property
    def latency_ms(self) -> float:
        """Arrival time minus the source frame's capture stamp (same host, or synchronised clocks)."""
        return (self.received_ns - self.pose.header.stamp_ns) / 1e6


class Feed:
    """One subscriber on ``key`` that decodes poses and hands each to ``sink`` (see the module docstring)."""

    def __init__(self, session: zenoh.Session, keys: Keys, key: str, sink: Callable[[PoseUpdate], None],
                 on_close: Callable[[Feed], None] | None = None):
        self.key = key
        self.received = 0
        self.decode_errors = 0
        self.sink_errors = 0
        self.last_stamp_ns: int | None = None
        self.latest: PoseUpdate | None = None
        self._keys = keys
        self._sink = sink
        self._arrived = threading.Event()
        self._closed = False
        self._on_close = on_close
        self._subscriber = session.declare_subscriber(key, self._on_sample)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        received_ns = time.time_ns()
        try:
            message = decode(sample.payload.to_bytes())
        except DecodeError as exc:
            self.decode_errors += 1
            log.warning("skipped a payload on %s: %s", sample.key_expr, exc)
            return
        if not isinstance(message, Pose):
            self.decode_errors += 1
            log.warning("skipped a %s on %s: not a Pose", type(message).__name__, sample.key_expr)
            return
        update = PoseUpdate(self._keys.target(str(sample.key_expr)), message, received_ns)
        self.received += 1
        self.last_stamp_ns = message.header.stamp_ns
        self.latest = update
        if not self._arrived.is_set():
            self._arrived.set()
        try:
            self._sink(update)
        except Exception:
            self.sink_errors += 1
            log.exception("the pose callback for %s failed (%d so far)", self.key, self.sink_errors)

    def wait(self, timeout_s: float) -> PoseUpdate | None:
        """The latest update, waiting up to ``timeout_s`` for a first one."""
        self._arrived.wait(timeout_s)
        return self.latest

    def state(self, dropped: int = 0) -> Subscription:
        return Subscription(key=self.key, received=self.received, dropped=dropped,
                            decode_errors=self.decode_errors, last_stamp_ns=self.last_stamp_ns)

    def close(self) -> None:
        """Undeclare the subscriber (once; later calls do nothing)."""
        if not self._closed:
            self._closed = True
            self._subscriber.undeclare()
            if self._on_close:
                self._on_close(self)


class _Overflow:
    """Counts updates dropped from a full queue and logs them at most once a second."""

    def __init__(self, key: str):
        self.key = key
        self.dropped = 0
        self._logged = -WARN_EVERY_S

    def count(self) -> None:
        self.dropped += 1
        now = time.monotonic()
        if now - self._logged >= WARN_EVERY_S:
            self._logged = now
            log.warning("the app reads poses on %s too slowly: dropped the oldest (%d so far)", self.key, self.dropped)


class PoseStream:
    """Iterate poses of the targets matching a key: ``for update in stream``.

    The loop ends when the stream is closed, or when nothing arrived for ``idle_timeout_s``
    (None: wait for ever). A target that nothing publishes gives an empty stream, never a hang
    past the idle timeout. Use as a context manager, or call ``close``.
    """

    def __init__(self, session: zenoh.Session, keys: Keys, key: str, *, idle_timeout_s: float | None = None,
                 depth: int = DEFAULT_DEPTH, on_close: Callable[[PoseStream], None] | None = None):
        self.idle_timeout_s = idle_timeout_s
        self._queue: queue.SimpleQueue[PoseUpdate] = queue.SimpleQueue()
        self._depth = depth
        self._overflow = _Overflow(key)
        self._closed = threading.Event()
        self._on_close = on_close
        self.feed = Feed(session, keys, key, self._put)

    @property
    def dropped(self) -> int:
        return self._overflow.dropped

    def _put(self, update: PoseUpdate) -> None:
        """Queue ``update`` (Zenoh's thread, the only producer), first dropping the oldest while full."""
        while self._queue.qsize() >= self._depth:
            try:
                self._queue.get_nowait()
                self._overflow.count()
            except queue.Empty:
                break
        self._queue.put(update)

    def __iter__(self) -> Iterator[PoseUpdate]:
        return self

    def __next__(self) -> PoseUpdate:
        idle_since = time.monotonic()
        while not self._closed.is_set():
            try:
                return self._queue.get(timeout=POLL_S)
            except queue.Empty:
                if self.idle_timeout_s is not None and time.monotonic() - idle_since >= self.idle_timeout_s:
                    break
        raise StopIteration

    def __enter__(self) -> PoseStream:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        if not self._closed.is_set():
            self._closed.set()
            self.feed.close()
            if self._on_close:
                self._on_close(self)


class AsyncPoseStream:
    """``async for update in stream``: the asyncio form of ``PoseStream`` (same ending rules).

    Create it from inside the running event loop; updates cross from Zenoh's thread to the
    loop with ``call_soon_threadsafe``.
    """

    def __init__(self, session: zenoh.Session, keys: Keys, key: str, *, idle_timeout_s: float | None = None,
                 depth: int = DEFAULT_DEPTH, on_close: Callable[[AsyncPoseStream], None] | None = None):
        self.idle_timeout_s = idle_timeout_s
        self._loop = asyncio.get_running_loop()
        self._queue: asyncio.Queue[PoseUpdate | None] = asyncio.Queue(maxsize=depth)
        self._overflow = _Overflow(key)
        self._closed = False
        self._on_close = on_close
        self.feed = Feed(session, keys, key, lambda update: self._loop.call_soon_threadsafe(self._put, update))

    @property
    def dropped(self) -> int:
        return self._overflow.dropped

    def _put(self, update: PoseUpdate | None) -> None:
        if self._queue.full():
            self._queue.get_nowait()
            self._overflow.count()
        self._queue.put_nowait(update)

    def __aiter__(self) -> AsyncIterator[PoseUpdate]:
        return self

    async def __anext__(self) -> PoseUpdate:
        if self._closed:
            raise StopAsyncIteration
        try:
            update = await asyncio.wait_for(self._queue.get(), self.idle_timeout_s)
        except TimeoutError:
            update = None
        if update is None:
            raise StopAsyncIteration
        return update

    async def __aenter__(self) -> AsyncPoseStream:
        return self

    async def __aexit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Stop the feed; a reader waiting in ``async for`` ends."""
        if not self._closed:
            self._closed = True
            self.feed.close()
            self._put(None)
            if self._on_close:
                self._on_close(self)
