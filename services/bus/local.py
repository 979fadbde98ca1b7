"""Deliveries between the nodes of one process: messages passed as Python objects, by reference.

Nodes composed into one process share one Zenoh session and one ``LocalBus``. A publisher of that
session hands each message to the local subscribers whose key expression takes its key (an
``Inbox`` gets the object itself: no encode, no copy, no decode), and puts it on Zenoh, encoded
once, only while a subscriber in another session matches the key (Zenoh's matching status). Its
Zenoh publisher sends to other sessions only, so nothing arrives twice and the matching status
counts only the subscribers that need the encoded bytes; what the session's other publishers put
(statistics, ends of stream) still reaches the local subscribers through Zenoh. A recorder's raw
taps want bytes: they get the same encoded payload as the bus does, encoded once for both. Once a
local subscriber has taken a message, its trip to the bus leaves from the process's ``Outbox``
(``services.bus.outbox``), so the subscriber is not kept waiting while the message is encoded.

A published message is immutable: a publisher does not change it (its arrays included) after
``put``, and a subscriber does not write into it. Decoded arrays are read-only, so a subscriber
that writes into a frame fails on frames from another process already.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Protocol

import zenoh

from protocol.message import Message
from services.bus.outbox import Outbox

Payload = Message | bytes
"""What a local subscriber is offered: the message itself, or the encoded bytes of a raw publisher."""


class LocalSink(Protocol):
    """A subscriber of the process: its key expression, and whether it wants encoded bytes."""

    key: str
    wants_bytes: bool

    def offer(self, key: str, payload: Payload) -> None:
        """Take ``payload`` published on ``key`` (called on the publisher's thread; must not block)."""
        ...


class LocalBus:
    """The subscribers of one process's nodes, found by the keys their expressions take, and the process's
    ``outbox`` of sends to the bus."""

    def __init__(self) -> None:
        self.outbox = Outbox()
        self._sinks: list[LocalSink] = []
        self._by_key: dict[str, tuple[LocalSink, ...]] = {}
        self._lock = threading.Lock()

    def attach(self, sink: LocalSink) -> None:
        with self._lock:
            self._sinks.append(sink)
            self._by_key.clear()

    def detach(self, sink: LocalSink) -> None:
        with self._lock:
            if sink in self._sinks:
                self._sinks.remove(sink)
            self._by_key.clear()

    def close(self) -> None:
        """Send what the outbox holds and stop its thread."""
        self.outbox.close()

    def sinks(self, key: str) -> tuple[LocalSink, ...]:
        """The subscribers whose key expression takes ``key`` (remembered per key until one comes or goes)."""
        found = self._by_key.get(key)
        if found is None:
            with self._lock:
                expression = zenoh.KeyExpr(key)
                found = tuple(s for s in self._sinks if zenoh.KeyExpr(s.key).intersects(expression))
                self._by_key[key] = found
        return found


def deliver(sinks: tuple[LocalSink, ...], key: str, message: Message, encoded: Callable[[], bytes]) -> None:
    """Offer ``message`` to ``sinks``: the object itself, or ``encoded()`` to those that want bytes."""
    for sink in sinks:
        sink.offer(key, encoded() if sink.wants_bytes else message)
