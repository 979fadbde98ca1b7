"""Replay node: a recording's bytes back onto their original keys, with their original timing.

Messages are published in file order (the order they reached the recorder), byte for byte,
on the key they were recorded from, at their log times scaled by ``rate`` (see
``playback``), so downstream nodes get the same inputs in the same order as live. Each
channel gets the QoS of its role, inferred from its schema: ``artrack.Image`` -> FRAME,
``artrack.NodeStats``/``ErrorReport`` -> STATUS, every other schema and raw payloads -> RESULT.

Selection: the channels whose key is included in one of ``keys`` (relative to the rig prefix
unless they start with the namespace); by default every channel except node health
(``<namespace>/*/node/**``: stats and error reports of the recorded nodes), which would
impersonate nodes that are not running. With ``retarget`` the keys of the rig the recording
was made on go out under the node's own namespace and rig (selection applies to the keys as
they go out), so a recording can drive a pipeline on any rig. ``start_s``/``end_s`` cut a window, in seconds from
the recording's first message. Before the first message the node waits up to ``wait_s`` for
a subscriber to match the selection, then ``SETTLE_S``, so the first messages are not
published before anyone can receive them.

Control: the queryable ``<prefix>/node/<name>/control`` takes a ``ReplayControl`` request
(``pause``, ``resume``, ``step``: publish the next message now, then stay paused; ``status``;
a query without payload asks for the status) and answers with a ``ReplayStatus`` once it has
obeyed; a request it cannot read gets an ``ErrorReport`` as an error reply, and is reported
on the node's errors key. ``artrack control NAME CMD`` sends them (``send_control``). With
``paused`` the node starts paused.

A damaged file is played up to its damage; one line then says where and why it stopped,
and ``run`` returns ``EXIT_DAMAGED`` (3).

Flow (``services.runtime.flow``): in a lossless run each image of a new frame waits for the
credits of the nodes taking the images before it goes out, and frames block rather than drop on
a congested bus. A replay that is not looping ends with an end of stream carrying the ``seq`` of
the last image it sent. The thread that plays waits for each message with a timer slack of 1 ns
(``services.runtime.pacing``), so messages go out closer to their due times.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar

import numpy as np
import zenoh
from mcap.records import Channel, Message, Metadata
from pydantic import BaseModel, ConfigDict, Field, model_validator

from protocol.codec import MEDIA_FRAME, MEDIA_JSON, DecodeError, decode, encode, peek
from protocol.keys import Keys
from protocol.message import Header
from protocol.sensors import Image
from protocol.system import ErrorReport, NodeStats, ReplayCommand, ReplayControl, ReplayStatus
from services.bus.pubsub import RawPublisher, Role
from services.recorder.info import summarise
from services.recorder.playback import LATENESS_KEPT, Pacer, Window, play_pass
from services.recorder.reading import EXIT_DAMAGED, Damage, NotMcap, Recorded, Scan
from services.recorder.writing import RECORDING_METADATA
from services.runtime.kind import NodeKind, SourceRole
from services.runtime.node import Node, NodeError
from services.runtime.pacing import sharpen
from services.runtime.stamps import SourceClock

SETTLE_S = 0.2
STEP_ANSWER_S = 1.0
"""How long a ``step`` waits for its message to go out before answering (at the end of the file none goes)."""
_ROLES = {Image.SCHEMA: Role.FRAME, NodeStats.SCHEMA: Role.STATUS, ErrorReport.SCHEMA: Role.STATUS}


class Params(BaseModel):
    """What to replay, how fast, and which part."""

    model_config = ConfigDict(extra="forbid")
    FLAGS: ClassVar[dict[str, str]] = {"start_s": "start", "end_s": "end", "wait_s": "wait"}

    path: Path
    rate: float = Field(default=1.0, gt=0, description="playback speed: 2 = twice as fast")
    loop: bool = False
    start_s: float = Field(default=0.0, ge=0, description="skip the first S seconds of the recording")
    end_s: float | None = Field(default=None, ge=0, description="stop S seconds into the recording")
    keys: tuple[str, ...] = Field(default=(), description="key expressions to replay; empty = all but node health")
    paused: bool = Field(default=False, description="start paused; resume with `artrack control NAME resume`")
    wait_s: float = Field(default=2.0, ge=0, description="wait up to S for a subscriber before the first message")
    restamp: bool = Field(default=False, description="give messages the time they are replayed as their stamp "
                                                     "(the recording's own clock from the first one's; "
                                                     "re-encodes them), to measure latency on a replay")
    retarget: bool = Field(default=False, description="publish the keys of the rig the recording was made on "
                                                       "under this node's namespace and rig instead")

    @model_validator(mode="after")
    def _window(self) -> Params:
        if self.end_s is not None and self.end_s <= self.start_s:
            raise ValueError(f"end_s ({self.end_s}) must be after start_s ({self.start_s})")
        return self

    def window(self) -> Window:
        return Window(int(self.start_s * 1e9), None if self.end_s is None else int(self.end_s * 1e9))


def role_of(channel_schema: str | None) -> Role:
    """The role whose QoS a channel is replayed with."""
    return _ROLES.get(channel_schema, Role.RESULT) if channel_schema else Role.RESULT


def recorded_prefix(path: Path) -> str:
    """``<namespace>/<rig>`` the recording at ``path`` was made on, from its ``artrack.recording`` metadata
    (written before its first message); ValueError naming the file when it has none."""
    for record in Scan(path).records():
        where = record.metadata if isinstance(record, Metadata) and record.name == RECORDING_METADATA else {}
        if "namespace" in where and "rig" in where:
            return f"{where['namespace']}/{where['rig']}"
        if isinstance(record, Message):
            break
    raise ValueError(f"{path}: no {RECORDING_METADATA} metadata naming its namespace and rig, so it cannot be "
                     f"replayed on another rig (retarget)")


class Retarget:
    """Recorded keys moved from the recording's ``<namespace>/<rig>/`` to ``keys``' prefix; others kept."""

    def __init__(self, recorded: str, keys: Keys):
        self._from = recorded + "/"
        self._to = keys.prefix + "/"

    def __call__(self, topic: str) -> str:
        return self._to + topic.removeprefix(self._from) if topic.startswith(self._from) else topic


def _as_recorded(topic: str) -> str:
    return topic


class Selection:
    """Which channels to replay (by the key they go out on), and the key expressions a subscriber must
    match to be waited for."""

    def __init__(self, keys: Keys, expressions: tuple[str, ...], topic: Callable[[str], str] = _as_recorded):
        self._topic = topic
        self.include = [zenoh.KeyExpr(keys.resolve(e)) for e in expressions]
        self.exclude = [] if expressions else [zenoh.KeyExpr(keys.all_node_keys())]
        self.probes = self.include or [zenoh.KeyExpr(keys.whole_namespace())]
        self._decided: dict[int, bool] = {}

    def __call__(self, channel: Channel) -> bool:
        chosen = self._decided.get(channel.id)
        if chosen is None:
            key = zenoh.KeyExpr(self._topic(channel.topic))
            chosen = self._decided[channel.id] = (
                (not self.include or any(e.includes(key) for e in self.include))
                and not any(e.includes(key) for e in self.exclude))
        return chosen


class _Restamper:
    """New stamps for replayed messages, one per recorded stamp and shared by every message of that stamp (an
    image and its CameraInfo stay joined): its place on the recording's own clock at ``rate``, from the
    wall-clock time the first one goes out (``SourceClock``), which a message that goes out late (held back
    by a slow node, or by a busy machine) does not move."""

    def __init__(self, rate: float = 1.0, kept: int = 4096):
        self._new: dict[int, int] = {}
        self._kept = kept
        self._clock = SourceClock()
        self._rate = rate
        self._first: int | None = None

    def __call__(self, payload: bytes) -> bytes:
        try:
            message = decode(payload)
        except DecodeError:
            return payload  # raw payloads go out as recorded
        old = message.header.stamp_ns
        if old not in self._new:
            if len(self._new) >= self._kept:
                self._new.pop(next(iter(self._new)))
            self._new[old] = self._scheduled(old)
        header = message.header.model_copy(update={"stamp_ns": self._new[old]})
        return encode(message.model_copy(update={"header": header}))

    def _scheduled(self, old: int) -> int:
        """The clock's stamp for recorded stamp ``old``, its own time counted from the first one's at ``rate``."""
        if self._first is None:
            self._first = old
        return self._clock.stamp(round((old - self._first) / self._rate))


class _Outputs:
    """One raw publisher per recorded channel, declared at its first message."""

    def __init__(self, node: Node, restamp: bool = False, topic: Callable[[str], str] = _as_recorded,
                 rate: float = 1.0):
        self._node = node
        self._topic = topic
        self._publishers: dict[int, RawPublisher] = {}
        self._credits = node.credits()
        self._restamp = _Restamper(rate) if restamp else None
        self._went_out = threading.Condition()
        self.published = 0
        self.frames = 0
        self.last_seq = -1

    def declare(self, recorded: Recorded) -> None:
        """Declare the publisher of ``recorded``'s channel unless it exists."""
        if recorded.channel.id in self._publishers:
            return
        schema = recorded.schema.name if recorded.schema is not None else None
        if schema is None:
            encoding = zenoh.Encoding.APPLICATION_OCTET_STREAM
        else:
            media = MEDIA_FRAME if recorded.channel.message_encoding == MEDIA_FRAME else MEDIA_JSON
            encoding = zenoh.Encoding(media).with_schema(schema)
        self._publishers[recorded.channel.id] = self._node.raw_publisher(self._topic(recorded.channel.topic),
                                                                         role_of(schema),
                                                                         encoding)

    def publish(self, recorded: Recorded) -> None:
        publisher = self._publishers[recorded.channel.id]
        data = recorded.message.data
        seq = _frame_seq(data) if publisher.role is Role.FRAME else None
        if seq is not None and self.frames and seq == self.last_seq:
            seq = None  # another camera's image of the frame already sent
        credits = self._credits
        if seq is not None and credits is not None and not credits.wait_for(seq, lambda: self._node.running):
            return
        started = time.perf_counter()
        publisher.put(self._restamp(data) if self._restamp else data)
        self._node.processed(time.perf_counter() - started)
        with self._went_out:
            self.published += 1
            self._went_out.notify_all()
        if seq is not None:
            if self._credits is not None:
                self._credits.sent(seq)
            self.frames += 1
            self.last_seq = seq


    def wait_beyond(self, published: int, timeout_s: float) -> None:
        """Block until more than ``published`` messages went out, or ``timeout_s`` passed."""
        with self._went_out:
            self._went_out.wait_for(lambda: self.published > published, timeout_s)


def _frame_seq(payload: bytes) -> int | None:
    """The ``header.seq`` of a recorded frame; None when it does not peek (it goes out all the same)."""
    try:
        return peek(payload).seq
    except DecodeError:
        return None


@dataclass
class Replayed:
    """What a replay did: messages published, passes over the file, the damage that ended
    the intact part (None: none met), and the lateness (ns) of the last publications."""

    played: int = 0
    passes: int = 0
    damage: Damage | None = None
    lateness_ns: deque[int] = field(default_factory=lambda: deque(maxlen=LATENESS_KEPT))


def replay(node: Node, params: Params) -> Replayed:
    """Play ``params.path`` onto the bus until it ends (or forever with ``loop``) or the node stops."""
    try:
        topic = Retarget(recorded_prefix(params.path), node.keys) if params.retarget else _as_recorded
    except ValueError as exc:
        raise NodeError(str(exc)) from exc
    selection = Selection(node.keys, params.keys, topic)
    pacer = Pacer(params.rate, paused=params.paused, running=lambda: node.running)
    outputs = _Outputs(node, params.restamp, topic, params.rate)
    done = Replayed()

    def on_query(query: zenoh.Query) -> None:
        now = Header(stamp_ns=time.time_ns())
        try:
            payload = query.payload
            request = ReplayControl(header=now) if payload is None else control_request(payload.to_bytes())
        except DecodeError as exc:
            node.report("bad_request", str(exc), str(query.key_expr))
            query.reply_err(encode(ErrorReport(header=now, node=node.name, kind="bad_request", detail=str(exc),
                                               key=str(query.key_expr))))
            return
        played = outputs.published
        if request.command is not ReplayCommand.STATUS:
            getattr(pacer, request.command.value)()
        if request.command is ReplayCommand.STEP:  # answer with the state after the step: its message out
            outputs.wait_beyond(played, STEP_ANSWER_S)
        query.reply(query.key_expr, encode(ReplayStatus(
            header=now, node=node.name, path=str(params.path), state=pacer.state, played=outputs.published,
            passes=done.passes, position_s=max(0, pacer.position_ns()) / 1e9, rate=params.rate)))

    queryable = node.session.declare_queryable(node.keys.control(node.name), on_query)
    try:
        _wait_for_subscriber(node, selection.probes, params.wait_s)
        if params.paused:
            node.log.info("paused; `artrack control %s resume` (or step) to go on", node.name)
        node.settle()
        sharpen()
        while node.running:
            result = play_pass(params.path, pacer, outputs.publish, select=selection, window=params.window(),
                               prepare=outputs.declare)
            done.passes += 1
            done.played += result.played
            done.lateness_ns.extend(result.lateness_ns)
            if result.damage is not None and done.damage is None:
                done.damage = result.damage
                node.log.warning("%s is damaged: %s, after %d intact messages (%.3f s into the recording); "
                                 "replayed everything before it", params.path, result.damage, result.read,
                                 result.last_ns / 1e9)
            if result.stopped or not params.loop or result.played == 0:
                break
        if node.running and not params.loop:
            node.end_of_stream(outputs.last_seq, outputs.frames)
    finally:
        queryable.undeclare()
    return done


def _wait_for_subscriber(node: Node, probes: list[zenoh.KeyExpr], wait_s: float) -> None:
    publishers = [node.session.declare_publisher(probe) for probe in probes]
    try:
        deadline = time.monotonic() + wait_s
        while not any(p.matching_status.matching for p in publishers):  # type: ignore[attr-defined]
            if time.monotonic() > deadline or not node.wait(0.01):
                node.log.info("no subscriber on %s after %.1f s; replaying anyway", ", ".join(map(str, probes)), wait_s)
                return
        node.wait(SETTLE_S)
    finally:
        for publisher in publishers:
            publisher.undeclare()


def run(node: Node, params: Params) -> int:
    """Replay and log what was done; the exit code (0, or ``EXIT_DAMAGED``)."""
    done = replay(node, params)
    line = f"replayed {done.played} messages of {params.path} ({done.passes} pass(es), rate {params.rate:g})"
    if done.lateness_ns:
        p50, p99, worst = np.percentile(np.array(done.lateness_ns) / 1e6, [50, 99, 100])
        line += f"; lateness p50 {p50:.2f} ms, p99 {p99:.2f} ms, max {worst:.2f} ms"
    node.log.info("%s", line)
    return EXIT_DAMAGED if done.damage is not None else 0


def control_request(payload: bytes) -> ReplayControl:
    """The ReplayControl in ``payload``; DecodeError when it holds anything else."""
    request = decode(payload)
    if not isinstance(request, ReplayControl):
        raise DecodeError(f"not a control request (expected {ReplayControl.SCHEMA})", schema=request.SCHEMA,
                          size=len(payload))
    return request


def send_control(session: zenoh.Session, keys: Keys, name: str, command: ReplayCommand,
                 timeout_s: float) -> ReplayStatus | None:
    """Send ``command`` to the control queryable of node ``name``; its ReplayStatus, or None when
    no such queryable appeared within ``timeout_s``; ValueError with the node's reason when it
    refused, or when its answer is not a ReplayStatus.

    A session that has just opened learns of remote queryables only as its links come up, so
    the query is sent once the queryable is known (a query sent earlier would reach nobody).
    """
    deadline = time.monotonic() + timeout_s
    querier = session.declare_querier(keys.control(name), timeout=timeout_s)
    request = ReplayControl(header=Header(stamp_ns=time.time_ns()), command=command)
    try:
        while not querier.matching_status.matching:  # type: ignore[attr-defined]  # a MatchingStatus
            if time.monotonic() > deadline:
                return None
            time.sleep(0.01)
        for reply in querier.get(payload=encode(request)):
            if reply.ok is None:
                reason = _refusal(reply.err.payload.to_bytes()) if reply.err is not None else "no reason given"
                raise ValueError(f"{name} refused {command.value}: {reason}")
            answer = decode(reply.ok.payload.to_bytes())
            if not isinstance(answer, ReplayStatus):
                raise ValueError(f"{name} answered {command.value} with {answer.SCHEMA}, not {ReplayStatus.SCHEMA}")
            return answer
        return None
    finally:
        querier.undeclare()


def _refusal(payload: bytes) -> str:
    """Why a control request was refused: the ErrorReport's detail, or the error reply's text."""
    try:
        report = decode(payload)
    except DecodeError:
        return payload.decode("utf-8", "replace")
    return report.detail if isinstance(report, ErrorReport) else f"a {report.SCHEMA} error reply"


def _outputs(params: Params) -> tuple[str, ...]:
    return tuple(params.keys) or ("**",)


def _check(params: Params) -> None:
    Scan(params.path)
    if params.retarget:
        recorded_prefix(params.path)


def _frame_sizes(params: Params) -> dict[str, tuple[int, int]]:
    """``{camera: (width, height)}`` of the first image of each camera replayed (``<camera>/image`` of the rig the
    recording was made on, within ``keys``); none for a recording that does not say its rig."""
    try:
        prefix = recorded_prefix(params.path)
    except ValueError:
        return {}
    namespace, _, rig = prefix.rpartition("/")
    selection = Selection(Keys(namespace, rig), params.keys)
    sizes: dict[str, tuple[int, int]] = {}
    for recorded in Scan(params.path).messages():
        camera = recorded.channel.topic.removeprefix(f"{prefix}/").partition("/")[0]
        if recorded.channel.topic != f"{prefix}/{camera}/image" or camera in sizes or not selection(recorded.channel):
            continue
        try:
            image = decode(recorded.message.data)
        except DecodeError:
            continue
        if isinstance(image, Image):
            sizes[camera] = (image.width, image.height)
    return sizes


def _frames(params: Params) -> int | None:
    """Frames per camera the replay will send (the fewest images on an image channel it selects, by the
    image keys in ``keys``, or on any when none are named); None when looping or when the file cannot be
    summed up."""
    if params.loop:
        return None
    try:
        channels = summarise(params.path).channels
    except (NotMcap, OSError):
        return None
    named = [key for key in params.keys if key.endswith("/image")]
    counts = [c.messages for c in channels if c.schema == Image.SCHEMA
              and (not named or any(c.key.endswith("/" + key) for key in named))]
    return min(counts) if counts else None


KIND = NodeKind(name="replay", summary="publishes a recording back onto its keys",
                params=Params, run=run, inputs=(), outputs=_outputs, check=_check,
                source=SourceRole(finite=lambda params: not params.loop, frames=_frames, fps=lambda params: None,
                                  wall_stamps=lambda params: False, sizes=_frame_sizes))
