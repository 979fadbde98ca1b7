"""A process's sends to the bus, made off the publishing thread while a local subscriber has work to do.

In a process group a publisher first hands a message to the process's own subscribers
(``services.bus.local``), then, when another session subscribes, encodes it and puts it on Zenoh.
Encoding and copying a 640x480 frame holds the interpreter for about a millisecond, which the
subscriber just handed the frame, a node thread of the same process, would otherwise wait out
before it could start. An ``Outbox`` takes such sends to one thread of its own: the publisher
returns at once, and the encoding overlaps the subscriber's work (OpenCV releases the interpreter
while it detects).

Each thread's sends leave in the order it put them: a send that needs no deferring (nothing local took
the message) still waits behind those its own thread queued, so a source's CameraInfo never overtakes
the image before it, nor its end of stream its last frames. Another thread's send does not wait for
them: one node's result goes out while the outbox is still encoding another node's frame, and two
nodes publishing at once (the blobs of two cameras) each put their own. A node's end of stream, which
goes to the bus directly, first waits for the outbox to empty (``runtime.node``). At most ``DEPTH``
sends wait; a publisher that would queue one more blocks until one has left, as an inline send would
have held it. ``flush`` returns once every send queued so far has left. A queued send that fails (the
session closing under it) is logged and dropped; one run at once raises to its publisher as before.
"""

from __future__ import annotations

import logging
import threading
from collections import deque
from collections.abc import Callable

log = logging.getLogger(__name__)

DEPTH = 32
"""Sends that may wait at most (each holds its message, a frame included, until it has left)."""

Send = Callable[[], None]


class Outbox:
    """Sends to the bus, each thread's in order, on one thread started with the first deferred send."""

    def __init__(self, depth: int = DEPTH):
        self.depth = depth
        self.failed = 0
        self._queue: deque[tuple[int, Send]] = deque()
        self._pending: dict[int, int] = {}
        self._busy = False
        self._closed = False
        self._changed = threading.Condition()
        self._thread: threading.Thread | None = None

    def send(self, send: Send, defer: bool) -> None:
        """Run ``send`` now when ``defer`` is false and nothing this thread queued waits before it, else queue
        it for the outbox's thread (after ``close``, always now)."""
        me = threading.get_ident()
        with self._changed:
            while not self._closed and (defer or self._pending.get(me)):
                if len(self._queue) < self.depth:
                    self._queue.append((me, send))
                    self._pending[me] = self._pending.get(me, 0) + 1
                    self._start()
                    self._changed.notify_all()
                    return
                self._changed.wait()
        send()

    def _start(self) -> None:
        if self._thread is None:
            self._thread = threading.Thread(target=self._drain, name="outbox", daemon=True)
            self._thread.start()

    def _drain(self) -> None:
        while True:
            with self._changed:
                while not self._queue:
                    if self._closed:
                        return
                    self._changed.wait()
                owner, send = self._queue.popleft()
                self._busy = True
            try:
                self._run(send)
            finally:
                with self._changed:
                    self._busy = False
                    self._pending[owner] -= 1
                    if not self._pending[owner]:
                        del self._pending[owner]
                    self._changed.notify_all()

    def _run(self, send: Send) -> None:
        try:
            send()
        except Exception as exc:  # noqa: BLE001 - one failed send (a session closing under it) must not stop the rest
            self.failed += 1
            log.warning("a send to the bus failed and was dropped: %s", exc)

    def flush(self, timeout_s: float = 2.0) -> bool:
        """Wait until every send queued so far has left (up to ``timeout_s``); whether they all did."""
        with self._changed:
            return self._changed.wait_for(lambda: not self._queue and not self._busy, timeout_s)

    def close(self, timeout_s: float = 2.0) -> None:
        """Send what waits (up to ``timeout_s``), then stop the thread; later sends run inline."""
        self.flush(timeout_s)
        with self._changed:
            self._closed = True
            self._changed.notify_all()
        if self._thread is not None:
            self._thread.join(timeout_s)
