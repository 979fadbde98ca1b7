"""Pose streams a client app reads, built on the bus's inbox and listener.

* ``PoseStream``: an ``Inbox`` of poses read by a plain ``for`` loop;
* ``AsyncPoseStream``: the same inbox read by ``async for`` (arrivals wake the event loop);
* ``Feed``: a ``Listener`` that hands each pose to a callback as it arrives (``Client.on_pose``)
  and keeps the latest (``Client.latest``).

Poses are results, never dropped silently: an app that reads too slowly loses its oldest
updates once ``depth`` are waiting, and the inbox counts them and logs it once per second.
Every stream reports its counts as a ``Subscription`` (``ClientState``, ``artrack status``).
"""

from __future__ import annotations

import asyncio
import logging
import threading
import time
from collections.abc import AsyncIterator, Callable, Iterator
from dataclasses import dataclass

import zenoh

from protocol.codec import DecodeError
from protocol.keys import Keys
from protocol.poses import Pose
from protocol.system import Subscription
from services.bus.pubsub import Inbox, Listener, Received, Role
from services.bus.stats import StreamCounter

log = logging.getLogger(__name__)

DEFAULT_DEPTH = 10_000
POLL_S = 0.1


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


def _skipped(key: str, error: DecodeError) -> None:
    log.warning("skipped a payload on %s: %s", key, error)


def _subscription(counter: StreamCounter, key: str, last_stamp_ns: int | None) -> Subscription:
    return Subscription(key=key, received=counter.messages, dropped=counter.dropped,
                        decode_errors=counter.decode_errors, last_stamp_ns=last_stamp_ns)


class Feed:
    """Poses on ``key`` handed to ``sink`` as they arrive (on Zenoh's thread); the latest is kept."""

    def __init__(self, session: zenoh.Session, keys: Keys, key: str, sink: Callable[[PoseUpdate], None],
                 on_close: Callable[[Feed], None] | None = None):
        self.key = key
        self.sink_errors = 0
        self.latest: PoseUpdate | None = None
        self._keys = keys
        self._sink = sink
        self._arrived = threading.Event()
        self._closed = False
        self._on_close = on_close
        self._listener = Listener(session, key, Pose, self._on_pose, on_decode_error=_skipped)

    def _on_pose(self, received: Received[Pose]) -> None:
        update = PoseUpdate(self._keys.target(received.key), received.message, received.received_ns)
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

    def state(self) -> Subscription:
        latest = self.latest
        return _subscription(self._listener.counter, self.key, latest.pose.header.stamp_ns if latest else None)

    def close(self) -> None:
        """Undeclare the subscriber (once; later calls do nothing)."""
        if not self._closed:
            self._closed = True
            self._listener.close()
            if self._on_close:
                self._on_close(self)


class _Stream:
    """What both stream forms share: the inbox, turning its messages into updates, and the counts."""

    def __init__(self, session: zenoh.Session, keys: Keys, key: str, depth: int,
                 notify: Callable[[], object] | None = None):
        self.key = key
        self._keys = keys
        self._last_stamp_ns: int | None = None
        self.inbox: Inbox[Pose] = Inbox(session, key, Pose, Role.RESULT, depth=depth, on_decode_error=_skipped,
                                        notify=notify)

    @property
    def dropped(self) -> int:
        return self.inbox.counter.dropped

    def _update(self, received: Received[Pose]) -> PoseUpdate:
        self._last_stamp_ns = received.message.header.stamp_ns
        return PoseUpdate(self._keys.target(received.key), received.message, received.received_ns)

    def state(self) -> Subscription:
        return _subscription(self.inbox.counter, self.key, self._last_stamp_ns)


class PoseStream(_Stream):
    """Iterate poses of the targets matching a key: ``for update in stream``.

    The loop ends when the stream is closed, or when nothing arrived for ``idle_timeout_s``
    (None: wait for ever). A target that nothing publishes gives an empty stream, never a hang
    past the idle timeout. Use as a context manager, or call ``close``.
    """

    def __init__(self, session: zenoh.Session, keys: Keys, key: str, *, idle_timeout_s: float | None = None,
                 depth: int = DEFAULT_DEPTH, on_close: Callable[[PoseStream], None] | None = None):
        super().__init__(session, keys, key, depth)
        self.idle_timeout_s = idle_timeout_s
        self._closed = threading.Event()
        self._on_close = on_close

    def __iter__(self) -> Iterator[PoseUpdate]:
        return self

    def __next__(self) -> PoseUpdate:
        idle_since = time.monotonic()
        while not self._closed.is_set():
            received = self.inbox.recv(POLL_S)
            if received is not None:
                return self._update(received)
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
            self.inbox.close()
            if self._on_close:
                self._on_close(self)


class AsyncPoseStream(_Stream):
    """``async for update in stream``: the asyncio form of ``PoseStream`` (same ending rules).

    Create it from inside the running event loop; each arrival sets an event on the loop
    (``call_soon_threadsafe``) and the loop takes the poses from the inbox.
    """

    def __init__(self, session: zenoh.Session, keys: Keys, key: str, *, idle_timeout_s: float | None = None,
                 depth: int = DEFAULT_DEPTH, on_close: Callable[[AsyncPoseStream], None] | None = None):
        self._loop = asyncio.get_running_loop()
        self._ready = asyncio.Event()
        super().__init__(session, keys, key, depth, notify=lambda: self._loop.call_soon_threadsafe(self._ready.set))
        self.idle_timeout_s = idle_timeout_s
        self._closed = False
        self._on_close = on_close

    def __aiter__(self) -> AsyncIterator[PoseUpdate]:
        return self

    async def __anext__(self) -> PoseUpdate:
        while not self._closed:
            self._ready.clear()
            received = self.inbox.take()
            if received is not None:
                return self._update(received)
            try:
                await asyncio.wait_for(self._ready.wait(), self.idle_timeout_s)
            except TimeoutError:
                break
        raise StopAsyncIteration

    async def __aenter__(self) -> AsyncPoseStream:
        return self

    async def __aexit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Stop the stream; a reader waiting in ``async for`` ends."""
        if not self._closed:
            self._closed = True
            self.inbox.close()
            self._ready.set()
            if self._on_close:
                self._on_close(self)
