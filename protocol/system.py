"""Messages about the service itself: node statistics, error reports, stage timings, client apps, replay control.

Their header's ``stamp_ns`` is the wall-clock time they were made and ``seq`` counts
them per node; ``frame_id`` is empty. ``StageTimings`` is the exception: it carries the
header of the frame it times.
"""

from __future__ import annotations

from enum import StrEnum
from typing import Literal

from pydantic import Field, field_validator

from protocol.message import Message, Struct

LATENCY_AGE_MAX_S = 10.0
"""The oldest input age ``NodeStats`` counts as latency (see there)."""


class StreamStats(Struct):
    """Counters of one subscribed (``in``) or published (``out``) key.

    ``dropped``: messages the node replaced or could not queue before it took them; ``missing``
    (frame inputs only): frames that never arrived, told by gaps in the ``header.seq`` of
    what did arrive and, once the source has ended, by the frames after the last one received.
    """

    key: str
    direction: Literal["in", "out"]
    messages: int = Field(default=0, ge=0)
    dropped: int = Field(default=0, ge=0)
    missing: int = Field(default=0, ge=0)
    decode_errors: int = Field(default=0, ge=0)
    rate_hz: float = Field(default=0.0, ge=0)


class SyncInputStats(Struct):
    """What became of one input's messages in a join (see ``SyncStats``)."""

    name: str
    key: str
    received: int = Field(default=0, ge=0)
    joined: int = Field(default=0, ge=0)
    evicted: int = Field(default=0, ge=0)
    superseded: int = Field(default=0, ge=0)
    out_of_order: int = Field(default=0, ge=0)

    @property
    def unjoined(self) -> int:
        """Messages that ended up in no set."""
        return self.evicted + self.superseded + self.out_of_order


class SyncStats(Struct):
    """One group of inputs a node joins into sets of one message each (``Node.synced``).

    ``by``: joined on equal header ``seq``, or on ``stamp`` within ``tolerance_ns`` of the
    first input's. ``sets`` complete sets were formed, ``dropped`` of them were replaced by
    a newer one before the node took them (latest-wins), ``resets`` times an input started
    over. Per input: ``joined`` went into a set; ``evicted`` were pushed out of a full buffer
    while waiting for partners; ``superseded`` were still waiting when a newer set went out;
    ``out_of_order`` arrived too old to join or repeated a pending key.
    """

    by: Literal["seq", "stamp"]
    tolerance_ns: int = Field(default=0, ge=0)
    sets: int = Field(default=0, ge=0)
    dropped: int = Field(default=0, ge=0)
    resets: int = Field(default=0, ge=0)
    inputs: tuple[SyncInputStats, ...] = ()


class NodeStats(Message):
    """A node's health, published periodically and answered on its state queryable.

    ``dropped`` counts frames a latest-wins input replaced before they were processed, and the complete
    sets a latest-wins join replaced so (``SyncStats.dropped``);
    ``decode_errors`` payloads that failed to decode or validate; ``processing_ms_p50``
    and ``_p99`` are over the last window of processed inputs; ``latency_ms_p50`` and ``_p99``
    over the same window are each input's age when the node was done with it (its outputs
    published): now minus the input's ``header.stamp_ns``, so for a tracker fed by a live
    capture, the pipeline's own latency up to this node. Only ages from 0 to
    ``LATENCY_AGE_MAX_S`` count: a replay stamped with the recording's time, or another
    host's clock, gives no figure (None) rather than a wrong one. ``skipped`` counts inputs
    the node could not use, by reason (``decode_error``, ``degenerate_homography``, ...);
    a source counts there too the frames it sent late, behind the pace asked (``late``).
    ``synced`` holds one entry per group of inputs the node joins; ``unjoined`` sums the
    messages of all groups that went into no set.

    ``missing`` sums the frames its inputs never received (``StreamStats.missing``): lost on
    the way, not dropped by the node. ``ended`` is true once the node has published its
    ``FlowEnd``: its sources ended and it has dealt with every frame they sent.

    Version 2 added ``synced``, version 3 ``missing`` and ``ended``; older payloads (older
    recordings) still decode, with none.
    """

    SCHEMA = "artrack.NodeStats"
    VERSION = 3
    READS_OLDER = (1, 2)

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
    missing: int = Field(default=0, ge=0)
    decode_errors: int = Field(default=0, ge=0)
    ended: bool = False
    processing_ms_p50: float | None = None
    processing_ms_p99: float | None = None
    latency_ms_p50: float | None = None
    latency_ms_p99: float | None = None
    skipped: dict[str, int] = Field(default_factory=dict)
    streams: tuple[StreamStats, ...] = ()
    synced: tuple[SyncStats, ...] = ()

    @property
    def unjoined(self) -> int:
        """Messages of joined inputs that went into no set (all groups, all reasons)."""
        return sum(i.unjoined for group in self.synced for i in group.inputs)


class ErrorReport(Message):
    """Something a node could not handle and skipped: what, where, how often so far."""

    SCHEMA = "artrack.ErrorReport"
    VERSION = 1

    node: str
    kind: str
    detail: str
    key: str = ""
    count: int = Field(default=1, ge=1)


class StageTimings(Message):
    """How long each stage of one frame's processing took in a node, milliseconds by stage name
    (``{"keypoints": 4.1, "match": 2.0, "pose": 1.2, "total": 8.0}``); the header is the frame's."""

    SCHEMA = "artrack.StageTimings"
    VERSION = 1

    stages_ms: dict[str, float] = Field(default_factory=dict)

    @field_validator("stages_ms")
    @classmethod
    def _durations(cls, value: dict[str, float]) -> dict[str, float]:
        negative = [stage for stage, ms in value.items() if ms < 0]
        if negative:
            raise ValueError(f"stage {negative[0]!r} took a negative time")
        return value


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


class SupervisedNode(Struct):
    """One node process of a pipeline as its supervisor sees it.

    ``state``: ``running``; ``backing_off`` (died, restart pending); ``failed`` (died more
    often than the restart budget allows, left down); ``finished`` (exited with code 0, or
    stopped). ``uptime_s`` is that of the current process (0 while down); ``exit_code`` the
    last one (negative: killed by that signal).
    """

    name: str
    kind: str
    state: Literal["running", "backing_off", "failed", "finished"]
    pid: int | None = None
    uptime_s: float = Field(default=0.0, ge=0)
    restarts: int = Field(default=0, ge=0)
    exit_code: int | None = None


class PipelineHealth(Message):
    """What an ``artrack up`` process supervises, answered on its health queryable."""

    SCHEMA = "artrack.PipelineHealth"
    VERSION = 1

    pipeline: str
    host: str
    pid: int
    uptime_s: float = Field(ge=0)
    nodes: tuple[SupervisedNode, ...] = ()


class ConfigChange(Message):
    """A request to change node parameters live: field name -> new value as JSON text."""

    SCHEMA = "artrack.ConfigChange"
    VERSION = 1

    values: dict[str, str] = Field(default_factory=dict)


class ConfigAnswer(Message):
    """A node's answer to a ConfigChange: all of it applied, or none of it with the reasons.

    ``applied`` maps each changed field to its new value as the node holds it (JSON text); ``refused`` maps each
    refused field to why. ``params`` holds every live-changeable field's value now.
    """

    SCHEMA = "artrack.ConfigAnswer"
    VERSION = 1

    node: str
    applied: dict[str, str] = Field(default_factory=dict)
    refused: dict[str, str] = Field(default_factory=dict)
    params: dict[str, str] = Field(default_factory=dict)


class ReplayCommand(StrEnum):
    """What a replay node is asked to do: ``step`` publishes the next message now and stays
    paused; ``status`` changes nothing."""

    PAUSE = "pause"
    RESUME = "resume"
    STEP = "step"
    STATUS = "status"


class ReplayControl(Message):
    """A request to a replay node's control queryable (``Keys.control``)."""

    SCHEMA = "artrack.ReplayControl"
    VERSION = 1

    command: ReplayCommand = ReplayCommand.STATUS


class ReplayStatus(Message):
    """A replay node's answer to a ReplayControl, once it has obeyed it.

    ``played`` counts the messages published so far (every pass), ``passes`` the passes begun
    over the file; ``position_s`` is the log time reached, in seconds from the recording's
    first message; ``rate`` the playback speed (2 = twice as fast). A request the node cannot
    read is answered with an ``ErrorReport`` instead (a Zenoh error reply).
    """

    SCHEMA = "artrack.ReplayStatus"
    VERSION = 1

    node: str
    path: str
    state: Literal["playing", "paused", "stopped"]
    played: int = Field(default=0, ge=0)
    passes: int = Field(default=0, ge=0)
    position_s: float = Field(default=0.0, ge=0)
    rate: float = Field(gt=0)
