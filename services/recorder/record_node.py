"""Recorder node: what travels on the rig's keys (or chosen key expressions) into MCAP files.

Each key expression gets a raw Zenoh subscriber whose callback only copies the payload,
stamps its arrival (``time.time_ns()``), peeks at what it is (``writing.identify``) and appends
it to a ``ByteQueue``. The node body is the writer thread: it takes arrivals in order,
writes them (``writing.RecordingWriter``) and flushes the open chunk every ``flush_s``, so a
``kill -9`` loses at most the last ``flush_s`` of data and leaves every earlier message
readable (``artrack info --recover`` re-indexes such a file). Nothing is latest-wins: an
arrival that does not fit the queue is dropped, counted (the node's ``dropped``), logged and
reported on the node's errors key at most once a second per key, and the count is written
into the file. Payloads that are not known artrack messages are recorded raw, counted as
decode errors and reported the same way.

A recorder that finds its file already begun refuses to start (a one-line error, exit 2), unless
the supervisor restarted it (``services.runtime.restarts``): then its predecessor was killed,
the file it left is kept as it is (readable up to its last flush), and the recording goes on in
the next continuation, ``OUT.part2.mcap``, ``OUT.part3.mcap``, ... (``writing.restart_target``),
whose ``artrack.recording`` metadata names ``OUT`` under ``continues``.

On SIGINT/SIGTERM the subscribers are undeclared, whatever Zenoh still had in flight is
delivered, the queue is drained and the file finished (summary and index): nothing that
arrived is lost.

Static data (``protocol.keys.Keys.latched``: static transforms, image targets) is published once, maybe
before the recorder subscribed; so, once subscribed, the recorder asks for the static keys its expressions
cover (``services.bus.latched``) and records the answers as they come, on their keys, like what is published.
A recorder there from the start may hold such a message twice (published and answered): the same data.

Flow (``services.runtime.flow``): images are counted by their ``header.seq``, so frames that
never arrived show as ``missing``; when the flow plan asks, each image written is acknowledged
(a lossless source waits for it), and once every upstream node has ended and all it published
is written, the recorder publishes its own end.
"""

from __future__ import annotations

import json
import threading
import time
from datetime import UTC, datetime
from pathlib import Path
from typing import ClassVar, Literal, TypeGuard

import zenoh
from pydantic import BaseModel, ConfigDict, Field, model_validator

from protocol.codec import Peeked, encode
from protocol.keys import Keys
from protocol.sensors import Image
from services.bus.latched import ask_latched
from services.bus.local import Payload
from services.bus.shm import received_bytes
from services.bus.stats import SeqGaps, StreamCounter
from services.recorder.byte_queue import ByteQueue
from services.recorder.writing import (
    Identity,
    RecordingWriter,
    Split,
    check_target,
    identify,
    message_class,
    restart_target,
)
from services.runtime.kind import NodeKind, SinkRole
from services.runtime.node import POLL_S, Node, NodeError
from services.runtime.restarts import restart_count

MB = 1 << 20
START = "{start}"
"""Placeholder in ``out`` for the UTC time the node starts, so a restarted recorder writes new files."""
CLOSE_S = 5.0
"""How long to wait, at the end, for Zenoh to deliver what it still had for a subscriber."""

Arrival = tuple[str, bytes, int, Identity]


class Params(BaseModel):
    """Where to record, what, and how to split and flush."""

    model_config = ConfigDict(extra="forbid")
    FLAGS: ClassVar[dict[str, str]] = {"split_size_mb": "split_size", "split_duration_s": "split_duration",
                                       "flush_s": "flush"}

    out: Path = Field(description=f"the file to write; {START} in its name becomes the UTC start time "
                                  "(e.g. 20261124T051000Z), a new name each time the node starts")
    keys: tuple[str, ...] = Field(default=(), description="key expressions, relative to the rig prefix unless "
                                                          "they start with the namespace; empty = the whole rig")
    split_size_mb: float | None = Field(default=None, gt=0, description="start a new part at this size (MiB)")
    split_duration_s: float | None = Field(default=None, gt=0, description="start a new part after this long")
    queue_mb: float = Field(default=512, gt=0, description="arrivals held while the writer is busy (MiB)")
    flush_s: float = Field(default=1.0, gt=0, description="write out the open chunk this often")
    compression: Literal["zstd", "lz4", "none"] = "zstd"

    @model_validator(mode="after")
    def _one_split(self) -> Params:
        if self.split_size_mb is not None and self.split_duration_s is not None:
            raise ValueError("split by size or by duration, not both")
        return self

    def target(self, started: datetime) -> Path:
        """``out`` with ``{start}`` replaced by ``started`` (UTC, ``YYYYmmddTHHMMSSZ``)."""
        stamp = started.astimezone(UTC).strftime("%Y%m%dT%H%M%SZ")
        return self.out.with_name(self.out.name.replace(START, stamp))

    def split(self) -> Split:
        return Split(size_bytes=None if self.split_size_mb is None else int(self.split_size_mb * MB),
                     duration_ns=None if self.split_duration_s is None else int(self.split_duration_s * 1e9))


class Tap:
    """One raw subscription feeding the queue; its counter is part of the node's stats.

    Messages published by nodes of the recorder's own process come encoded from their publisher
    (the recorder writes bytes), the others' through Zenoh.
    """

    wants_bytes = True

    def __init__(self, node: Node, key: str, queue: ByteQueue[Arrival]):
        self.key = key
        self.counter = node.track(StreamCounter(key, "in"))
        self._node = node
        self._queue = queue
        self._gaps = SeqGaps()
        self._lock = threading.Lock()
        self._delivered = threading.Event()  # Zenoh calls the drop callback after the last sample
        self._subscriber = node.session.declare_subscriber(
            key, zenoh.handlers.Callback(self._on_sample, self._delivered.set))
        node.host.local.attach(self)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        if sample.kind != zenoh.SampleKind.PUT:  # a deletion carries no payload to record or replay
            return
        self.offer(str(sample.key_expr), received_bytes(sample.payload))

    def offer(self, key: str, message: Payload) -> None:
        """Queue what arrived on ``key``, as the bytes it is (or is encoded to)."""
        arrived = time.time_ns()
        payload = message if isinstance(message, bytes) else encode(message)
        identity = identify(payload)
        missing = 0
        if _is_image(identity):
            with self._lock:
                missing = self._gaps.note(key, identity.seq)
        queued = self._queue.put((key, payload, arrived, identity), len(payload))
        unknown = message_class(identity) is None
        self.counter.count(messages=1, dropped=int(not queued), decode_errors=int(unknown), missing=missing, key=key)
        if not queued:
            self._node.report("queue_full", f"recorder queue full ({self._queue.nbytes / MB:.0f} MiB held), "
                                            f"a {len(payload)}-byte message was dropped", key)
        if unknown:
            self._node.report("unrecognised", f"recorded raw: {identity}", key)

    def count_tail(self, last_seq: int) -> int:
        """Count as missing the images after the last one received, up to the source's ``last_seq``."""
        with self._lock:
            missing = self._gaps.tail(last_seq)
        self.counter.count(missing=missing)
        return missing

    def close(self) -> bool:
        """Undeclare; True once Zenoh has delivered everything it had for this subscriber."""
        self._node.host.local.detach(self)
        self._subscriber.undeclare()
        return self._delivered.wait(CLOSE_S)


def subscriptions(keys: Keys, expressions: tuple[str, ...]) -> list[str]:
    """The key expressions to subscribe to (the whole rig when none are given), none inside
    another; ValueError for two that overlap otherwise, since a message on both would be
    recorded twice."""
    chosen: list[zenoh.KeyExpr] = []
    for expression in [keys.resolve(e) for e in expressions] or [keys.everything()]:
        new = zenoh.KeyExpr(expression)
        if any(old.includes(new) for old in chosen):
            continue
        chosen = [old for old in chosen if not new.includes(old)]
        clash = next((old for old in chosen if old.intersects(new)), None)
        if clash is not None:
            raise ValueError(f"key expressions {clash} and {new} overlap: a message on both would be recorded twice")
        chosen.append(new)
    return [str(k) for k in chosen]


def run(node: Node, params: Params) -> None:
    keys = subscriptions(node.keys, params.keys)
    named = params.target(datetime.now(UTC))
    queue: ByteQueue[Arrival] = ByteQueue(int(params.queue_mb * MB))
    taps: list[Tap] = []

    def notes() -> dict[str, str]:
        totals = [t.counter.snapshot() for t in taps]
        return {"received": str(sum(s.messages for s in totals)), "dropped": str(sum(s.dropped for s in totals)),
                "unrecognised": str(sum(s.decode_errors for s in totals))}

    out = named
    try:
        if restart_count():
            out = restart_target(named)
        check_target(out)
        metadata = {"namespace": node.keys.namespace, "rig": node.keys.rig, "keys": json.dumps(keys),
                    **({"continues": named.name} if out != named else {})}
        writer = RecordingWriter(out, split=params.split(), compression=params.compression, notes=notes,
                                 metadata=metadata)
    except ValueError as exc:
        raise NodeError(str(exc)) from exc
    except OSError as exc:
        raise NodeError(f"cannot record to {out}: {exc.strerror or exc}") from exc
    if out != named:
        node.log.warning("restarted: %s was begun by the recorder before this one; going on in %s", named, out)
    try:
        try:
            taps += [Tap(node, key, queue) for key in keys]
            for tap in taps:
                ask_latched(node.session, tap.key, node.keys.latched(), tap.offer)
            node.log.info("recording %s to %s", ", ".join(keys), writer.files[0])
            node.ready()
            flush_at = time.monotonic() + params.flush_s
            while node.running:
                arrival = queue.get(POLL_S)
                if arrival is not None:
                    _write(node, writer, arrival)
                elif not node.ended and node.end_when_done(taps):
                    writer.flush()
                if time.monotonic() >= flush_at:
                    writer.flush()
                    flush_at = time.monotonic() + params.flush_s
        finally:
            for tap in taps:
                if not tap.close():
                    node.log.warning("%s: Zenoh did not deliver its last samples within %.0f s", tap.key, CLOSE_S)
        while (arrival := queue.get(0)) is not None:
            _write(node, writer, arrival)
    finally:
        writer.close()
        counts = notes()
        node.log.info("recorded %d messages (%.1f MiB of payload) in %s; %s dropped (queue full), %s unrecognised "
                      "(recorded raw)", writer.messages, writer.payload_bytes / MB,
                      ", ".join(map(str, writer.files)), counts["dropped"], counts["unrecognised"])


def _write(node: Node, writer: RecordingWriter, arrival: Arrival) -> None:
    started = time.perf_counter()
    writer.write(*arrival)
    node.processed(time.perf_counter() - started)
    identity = arrival[3]
    if _is_image(identity):
        node.ack(identity.seq)


def _is_image(identity: Identity) -> TypeGuard[Peeked]:
    return isinstance(identity, Peeked) and identity.cls is Image


def _inputs(params: Params) -> tuple[str, ...]:
    return tuple(params.keys) or ("**",)


def _check(params: Params) -> None:
    check_target(params.out)


KIND = NodeKind(name="recorder", summary="records the rig's keys to MCAP files",
                params=Params, run=run, inputs=_inputs, outputs=(), check=_check,
                sink=SinkRole(files=lambda params: (("recording", params.out),)))
