"""A FIFO bounded by the total size of what it holds, for the recorder's arrivals.

``put`` never blocks (it runs on Zenoh's callback thread): when an item would take the
queue over its capacity it is refused and the caller counts it. One item larger than the
whole capacity is still accepted when the queue is empty, so no size of message is
refused for its size alone.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from typing import Generic, TypeVar

T = TypeVar("T")


class ByteQueue(Generic[T]):
    """Thread-safe FIFO of ``(item, nbytes)`` holding at most ``capacity_bytes`` in total."""

    def __init__(self, capacity_bytes: int):
        self.capacity_bytes = capacity_bytes
        self._items: deque[tuple[T, int]] = deque()
        self._bytes = 0
        self._ready = threading.Condition()

    def put(self, item: T, nbytes: int) -> bool:
        """Queue ``item`` (of ``nbytes``); False, and nothing queued, when it does not fit."""
        with self._ready:
            if self._items and self._bytes + nbytes > self.capacity_bytes:
                return False
            self._items.append((item, nbytes))
            self._bytes += nbytes
            self._ready.notify()
            return True

    def get(self, timeout_s: float) -> T | None:
        """The oldest item, waiting up to ``timeout_s`` for one; None when none came."""
        deadline = time.monotonic() + timeout_s
        with self._ready:
            while not self._items:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return None
                self._ready.wait(remaining)
            item, nbytes = self._items.popleft()
            self._bytes -= nbytes
            return item

    @property
    def nbytes(self) -> int:
        """Bytes held now."""
        return self._bytes

    def __len__(self) -> int:
        return len(self._items)
