"""Messages about the service itself: node statistics, error reports, client apps.

Their header's ``stamp_ns`` is the wall-clock time they were made and ``seq`` counts
them per node; ``frame_id`` is empty.
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from protocol.message import Message, Struct


class StreamStats(Struct):
    """Counters of one subscribed (``in``) or published (``out``) key."""

    key: str
    direction: Literal["in", "out"]
    messages: int = Field(default=0, ge=0)
    dropped: int = Field(default=0, ge=0)
    decode_errors: int = Field(default=0, ge=0)
    rate_hz: float = Field(default=0.0, ge=0)


class NodeStats(Message):
    """A node's health, published periodically and answered on its state queryable.

    ``dropped`` counts frames a latest-wins input replaced before they were processed;
    ``decode_errors`` payloads that failed to decode or validate; ``processing_ms_p50``
    and ``_p99`` are over the last window of processed inputs; ``skipped`` counts inputs
    the node could not use, by reason (``decode_error``, ``degenerate_homography``, ...).
    """

    SCHEMA = "artrack.NodeStats"
    VERSION = 1

    node: str
    kind: str
    host: str
    pid: int
    state: Literal["starting", "running", "stopping"] = "running"
    uptime_s: float = Field(ge=0)
    received: int = Field(default=0, ge=0)
    published: int = Field(default=0, ge=0)
    processed: int = Field(default=0, ge=0)
    dropped: int = Field(default=0, ge=0)
    decode_errors: int = Field(default=0, ge=0)
    processing_ms_p50: float | None = None
    processing_ms_p99: float | None = None
    skipped: dict[str, int] = Field(default_factory=dict)
    streams: tuple[StreamStats, ...] = ()


class ErrorReport(Message):
    """Something a node could not handle and skipped: what, where, how often so far."""

    SCHEMA = "artrack.ErrorReport"
    VERSION = 1

    node: str
    kind: str
    detail: str
    key: str = ""
    count: int = Field(default=1, ge=1)


class Subscription(Struct):
    """One stream a client app asked for: the key expression, and what it has had from it."""

    key: str
    received: int = Field(default=0, ge=0)
    dropped: int = Field(default=0, ge=0)
    decode_errors: int = Field(default=0, ge=0)
    last_stamp_ns: int | None = None


class ClientState(Message):
    """A client app's view of the service, answered on its state queryable (``artrack status``)."""

    SCHEMA = "artrack.ClientState"
    VERSION = 1

    client: str
    app: str
    host: str
    pid: int
    uptime_s: float = Field(ge=0)
    subscriptions: tuple[Subscription, ...] = ()
