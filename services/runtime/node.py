"""A node: one process's presence on the bus, its inputs, outputs and health.

A node body is a short loop over its inputs::

    def run(node: Node, params: Params) -> None:
        frames = node.inbox(node.keys.image(params.camera), Image, Role.FRAME)
        out = node.publisher(node.keys.echo(params.camera), Image, Role.FRAME)
        for image in node.inputs(frames):
            out.put(image)

A body that needs one message from each of several inputs at once (the two images of a
stereo rig, a frame with its detections) iterates joined sets instead::

    pairs = node.synced({"left": node.keys.image("left"), "right": node.keys.image("right")}, Image)
    for pair in pairs:
        match(pair["left"], pair["right"])

While it runs, the node holds a liveliness token at ``keys.node(name)`` (what ``artrack
list`` shows; a name another live process holds on the rig is refused with ``NameTaken``),
publishes ``NodeStats`` every ``stats_period_s`` on ``keys.stats(name)`` (and once more as it
closes, its final counts), answers the same on the ``keys.state(name)`` queryable, and reports
inputs it had to skip (``report``) on ``keys.errors(name)``. A body that calls
``configurable`` also answers live parameter changes on ``keys.config(name)``
(``services.runtime.reconfig``). ``run_node`` adds SIGINT/SIGTERM handling: the loop ends
within a poll period (0.1 s) and everything is undeclared and closed.

Flow (``services.runtime.flow``): with a lossless ``FlowPlan`` frame inputs queue every frame
and frame outputs block rather than drop; a node that ``acks`` acknowledges each frame it has
dealt with once its body asks for the next input; a source calls ``end_of_stream`` after its
last frame, and any other node publishes its own end, while it waits for input, once every
node of its ``upstream`` has ended and everything they published has arrived and been dealt with.
"""

from __future__ import annotations

import logging
import os
import signal
import socket
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import asdict
from typing import Generic, Literal, Protocol, TypeVar

import zenoh
from pydantic import BaseModel

from protocol.codec import DecodeError, decode, encode
from protocol.flow import FlowAck, FlowEnd
from protocol.keys import Keys
from protocol.message import Header, Message
from protocol.system import ConfigAnswer, ConfigChange, ErrorReport, NodeStats, SyncInputStats, SyncStats
from services.bus.discovery import every_answer, token_held
from services.bus.pubsub import Inbox, Publisher, RawPublisher, Role
from services.bus.session import BusConfig, BusError
from services.bus.stats import AgeWindow, LatencyWindow, StreamCounter
from services.runtime.flow import Credits, Ends, FlowPlan, end_message
from services.runtime.host import Host
from services.runtime.memory import settle_heap
from services.runtime.pacing import wait_until
from services.runtime.reconfig import LiveParams
from services.runtime.restarts import EXIT_CANNOT_RUN
from services.runtime.sync import JoinBy, Joiner, join_key, key_tolerance

M = TypeVar("M", bound=Message)
P = TypeVar("P", bound=BaseModel)
T = TypeVar("T")

POLL_S = 0.1
LINGER_S = 0.5
REPORT_EVERY_S = 1.0
LINKS_S = 2.0
"""How long a new node waits for its session's first link before asking whether its name is taken."""
LOOK_S = 0.3
"""How long a new node keeps asking whether its name's token is held before taking it as free."""
STALE_S = 1.0
"""How long a token must stay held to count as a live holder of the name (see ``_refuse_taken_name``)."""
GONE_S = 0.5
"""How long a token seen before must go unseen to count as gone."""
NAME_QUERY_S = 0.5
POLL_NAME_S = 0.05
DEFAULT_SYNC_DEPTH = 8
LOSSLESS_DEPTH = 100_000
"""Frames a lossless input may hold: in practice the source's credits bound it to its window."""
END_GRACE_S = 2.0
"""How long a node whose upstream nodes have all ended waits for messages they published that have
not arrived, once nothing arrives any more, before it ends with them counted as missing."""


class Tapped(Protocol):
    """An input as the end of stream sees it: its key expression, its counts and its frame gaps."""

    key: str
    counter: StreamCounter

    def count_tail(self, last_seq: int) -> int: ...


class NodeError(RuntimeError):
    """A node cannot do its job (a missing camera, a bad file): the message says what and why.

    ``run_node`` logs it as one line, without a traceback, and exits with code 2 (``EXIT_CANNOT_RUN``): a
    supervisor does not restart it.
    """


class NameTaken(NodeError):
    """Another live process already holds the node's name on its rig."""


def _refuse_taken_name(session: zenoh.Session, keys: Keys, name: str) -> None:
    """NameTaken, saying who holds it, when another process holds the liveliness token of node ``name``.

    The question is asked again and again: a session that has just opened hears of the tokens
    on the bus only as its links come up, and an answer may come back empty now and then though
    the token is there, so one "held" counts, and only a token unseen for ``GONE_S`` has gone.
    A process that died leaves the bus with its session, its token with it; one killed hard
    leaves as soon as its router sees the connection drop, which takes a moment: a token must
    still be seen ``STALE_S`` after it was first seen to refuse the name, so a node restarted
    after a crash is not refused by its own former process. Two nodes that miss each other
    here (a loaded machine, both starting at once) meet later: see ``Node._yield_to_an_elder``.
    """
    links_by = time.monotonic() + LINKS_S
    while not (session.info.routers_zid() or session.info.peers_zid()) and time.monotonic() < links_by:
        time.sleep(POLL_NAME_S)
    key = keys.node(name)
    look_by = time.monotonic() + LOOK_S
    while not token_held(session, key, NAME_QUERY_S):
        if time.monotonic() >= look_by:
            return
        time.sleep(POLL_NAME_S)
    first_seen = last_seen = time.monotonic()
    while last_seen - first_seen < STALE_S:
        time.sleep(POLL_NAME_S)
        now = time.monotonic()
        if token_held(session, key, NAME_QUERY_S):
            last_seen = now
        elif now - last_seen >= GONE_S:
            return
    raise NameTaken(_taken_message(name, keys, [stats for _, stats in every_answer(
        session, keys.state(name), NodeStats, NAME_QUERY_S)]))


def _taken_message(name: str, keys: Keys, holders: list[NodeStats], doing: str = "not starting a second one") -> str:
    """One line: node ``name`` is already held on the rig, by ``holders`` (as their state says), so ``doing``."""
    who = "; ".join(f"pid {s.pid} on {s.host}, kind {s.kind}, up {s.uptime_s:.0f} s" for s in holders)
    return (f"node {name} is already running on {keys.prefix} ({who or 'its state did not answer'}): "
            f"{doing} (stop it, or give this one another name or rig)")


class Node:
    """A named participant on the bus (see the module docstring)."""

    def __init__(self, name: str, kind: str, bus: BusConfig, *, stats_period_s: float = 1.0,
                 flow: FlowPlan | None = None, host: Host | None = None):
        self.name = name
        self.flow = flow or FlowPlan()
        self.kind = kind
        self.bus = bus
        self.keys = bus.keys
        self.log = logging.getLogger(f"artrack.{kind}")
        self._stop = threading.Event()
        self.serving = threading.Event()
        """Set once the node's inputs are subscribed and it waits for them (``ready``)."""
        self._wake = threading.Condition()
        self._started = time.monotonic()
        self._inboxes: list[Inbox] = []
        self._syncs: list[Synced] = []
        self._publishers: list[Publisher | RawPublisher] = []
        self._answers: list[zenoh.Queryable] = []
        self._tracked: list[StreamCounter] = []
        self._processing = LatencyWindow()
        self._ages = AgeWindow()
        self._processed = 0
        self._stats_seq = 0
        self._state: Literal["starting", "running", "stopping"] = "starting"
        self._errors: dict[tuple[str, str], int] = {}
        self._last_report: dict[tuple[str, str], float] = {}
        self._stats_period_s = stats_period_s
        self.taken: str | None = None
        self.failure: str | None = None
        """Why the node's body failed, in one line (set by ``serve``)."""
        """Why the node stopped itself: another process holds its name (see ``_yield_to_an_elder``)."""
        self._started_ns = time.time_ns()
        self._ready = False
        self._ended: FlowEnd | None = None
        self._acked: FlowAck | None = None
        self._short_since: float | None = None
        self._short_total = -1
        self._credits: list[Credits] = []
        self._owns_host = host is None
        self.host = Host(bus) if host is None else host
        self.session = self.host.session
        try:
            _refuse_taken_name(self.session, self.keys, name)
            self._token = self.session.liveliness().declare_token(self.keys.node(name))
            self._stats_pub = Publisher(self.session, self.keys.stats(name), NodeStats, Role.STATUS)
            self._errors_pub = Publisher(self.session, self.keys.errors(name), ErrorReport, Role.STATUS)
            self._queryable = self.session.declare_queryable(self.keys.state(name), self._on_state_query)
            self._ack_pub = Publisher(self.session, self.keys.ack(name), FlowAck, Role.RESULT)
            self._end_pub = Publisher(self.session, self.keys.end(name), FlowEnd, Role.END)
            self._last_stats_pub = Publisher(self.session, self.keys.stats(name), NodeStats, Role.END)
            self._end_answer = self.session.declare_queryable(self.keys.end(name), self._on_end_query)
            self._ack_answer = self.session.declare_queryable(self.keys.ack(name), self._on_ack_query)
            self._ends = Ends(self.session, self.keys, self.flow.upstream, self._poke) if self.flow.upstream else None
        except Exception:
            self._close_host()
            raise
        self._stats_thread = threading.Thread(target=self._stats_loop, name=f"{name}-stats", daemon=True)
        self._stats_thread.start()

    def __enter__(self) -> Node:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def running(self) -> bool:
        return not self._stop.is_set()

    @property
    def ended(self) -> bool:
        """Whether the node has published its end of stream."""
        return self._ended is not None

    def _poke(self) -> None:
        with self._wake:
            self._wake.notify_all()

    def stop(self) -> None:
        """Ask the node's loops to end (safe from signal handlers and other threads)."""
        self._stop.set()
        for credits in self._credits:
            credits.stop()
        with self._wake:
            self._wake.notify_all()

    def wait(self, seconds: float) -> bool:
        """Sleep up to ``seconds``, waking early when stopped; return whether still running."""
        if seconds > 0:
            self._stop.wait(seconds)
        return self.running

    def wait_until(self, due: float) -> bool:
        """Sleep until ``time.monotonic()`` reaches ``due``, the calling thread's timer slack out of the way
        (``services.runtime.pacing``), waking early when stopped; return whether still running."""
        return wait_until(due, self._stop)

    def publisher(self, key: str, cls: type[M], role: Role = Role.RESULT) -> Publisher[M]:
        publisher = Publisher(self.session, key, cls, role, StreamCounter(key, "out"), self.flow.lossless,
                              self.host.local)
        self._publishers.append(publisher)
        return publisher

    def raw_publisher(self, key: str, role: Role, encoding: zenoh.Encoding) -> RawPublisher:
        """A publisher of already encoded payloads (replay), counted in the node's stats."""
        publisher = RawPublisher(self.session, key, role, encoding, StreamCounter(key, "out"), self.flow.lossless,
                                 self.host.local)
        self._publishers.append(publisher)
        return publisher

    def answer(self, key: str, reply: Callable[[], Message | None]) -> None:
        """Answer queries on ``key`` with the message ``reply()`` returns at the time (none when None)."""

        def on_query(query: zenoh.Query) -> None:
            message = reply()
            if message is not None:
                query.reply(key, encode(message))

        self._answers.append(self.session.declare_queryable(key, on_query))

    def configurable(self, params: P, apply: Callable[[P], None] | None = None) -> LiveParams[P]:
        """Let the reloadable fields of ``params`` change while the node runs (``keys.config(name)``).

        The body reads ``.value`` of the result for the current parameters; ``apply(new)``
        puts changed ones to work first and may raise ValueError to refuse them.
        """
        live = LiveParams(params, apply)

        def on_query(query: zenoh.Query) -> None:
            try:
                change = decode(query.payload.to_bytes()) if query.payload is not None else None
            except DecodeError as exc:
                change = None
                self.report("decode_error", str(exc), str(query.key_expr))
            if not isinstance(change, ConfigChange):
                answer = ConfigAnswer(header=Header(stamp_ns=time.time_ns()), node=self.name,
                                      refused={"(request)": "expected a ConfigChange payload"},
                                      params=live.reloadable_values())
            else:
                answer = live.answer(self.name, change)
                if answer.applied:
                    self.log.info("parameters changed live: %s", answer.applied, extra={"applied": answer.applied})
                elif answer.refused:
                    self.log.warning("parameter change refused: %s", answer.refused, extra={"refused": answer.refused})
            query.reply(self.keys.config(self.name), encode(answer))

        self._answers.append(self.session.declare_queryable(self.keys.config(self.name), on_query))
        return live

    def track(self, counter: StreamCounter) -> StreamCounter:
        """Count a stream the body serves with its own Zenoh entities (the recorder's raw
        subscribers) in the node's stats, by the counter's direction."""
        self._tracked.append(counter)
        return counter

    def inbox(self, key: str, cls: type[M] | None, role: Role = Role.FRAME, depth: int | None = None) -> Inbox[M]:
        """Messages on ``key``; frames keep the newest ``depth`` (every one in a lossless run)."""
        if self.flow.lossless and role is Role.FRAME:
            depth = LOSSLESS_DEPTH
        inbox = Inbox(self.session, key, cls, role, depth=depth, counter=StreamCounter(key, "in"),
                      on_decode_error=self._on_decode_error, wake=self._wake, local=self.host.local)
        self._inboxes.append(inbox)
        return inbox

    def inputs(self, *inboxes: Inbox[M]) -> Iterator[M]:
        """Messages from ``inboxes`` (taken in turn) until the node stops.

        The time between handing out a message and being asked for the next one is the
        node's processing time for it.
        """
        turn = 0
        frame = False

        def take() -> M | None:
            nonlocal turn, frame
            for i in range(len(inboxes)):
                inbox = inboxes[(turn + i) % len(inboxes)]
                received = inbox.take()
                if received is not None:
                    turn = (turn + i + 1) % len(inboxes)
                    frame = inbox.role is Role.FRAME
                    return received.message
            return None

        return self._serve(take, inboxes, lambda message: message.header.stamp_ns,
                           lambda message: message.header.seq if frame else None)

    def synced(self, inputs: Mapping[str, str], cls: type[M] | Mapping[str, type[Message] | None] | None,
               role: Role = Role.FRAME, *, by: JoinBy = "seq", tolerance_s: float = 0.0,
               depth: int = DEFAULT_SYNC_DEPTH, backlog: int | None = None) -> Synced:
        """Sets of one message from each of ``inputs`` ({name: key}), joined on their headers.

        ``by="seq"`` joins messages with equal ``header.seq``; ``by="stamp"`` joins those whose
        ``header.stamp_ns`` lies within ``tolerance_s`` of the first input's. ``cls`` is one
        message type for all inputs or one per name. Each input keeps up to ``depth`` messages
        waiting for partners. ``role=Role.FRAME`` is latest-wins: each input queues up to
        ``depth`` messages, and only the newest complete set is handed out. Any other role
        hands out every set in order, its inputs queueing as that role does. A ``backlog`` makes
        any role's sets latest-wins in real time: the newest ``backlog`` complete sets wait, handed
        out oldest first, and older ones are dropped and counted; a lossless flow hands out every set.
        Iterate the result for ``{name: message}`` dicts in ``inputs``' order, as ``inputs`` hands out messages;
        what could not be joined is counted in ``NodeStats.synced`` (``services.runtime.sync``
        says how).
        """
        tolerance_ns = key_tolerance(by, tolerance_s)
        types = cls if isinstance(cls, Mapping) else dict.fromkeys(inputs, cls)
        if set(types) != set(inputs):
            raise ValueError(f"cls names {sorted(types)}, but the inputs are {sorted(inputs)}")
        latest = (role is Role.FRAME or backlog is not None) and not self.flow.lossless
        if role is Role.FRAME and self.flow.lossless:
            depth = LOSSLESS_DEPTH
        joiner: Joiner[M] = Joiner(list(inputs), tolerance=tolerance_ns, depth=depth,
                                   ready=(backlog or 1) if latest else depth)
        queued = depth if latest and role is Role.FRAME else None
        inboxes = {name: self.inbox(key, types[name], role, queued) for name, key in inputs.items()}
        synced = Synced(self, inboxes, joiner, by, latest)
        self._syncs.append(synced)
        return synced

    def _serve(self, take: Callable[[], T | None], inboxes: Sequence[Inbox], stamp: Callable[[T], int],
               seq: Callable[[T], int | None]) -> Iterator[T]:
        """What ``take()`` hands out until the node stops, waiting on ``inboxes`` while it has nothing;
        ``stamp(item)`` is the stamp whose age counts as the node's latency, ``seq(item)`` the frame it
        acknowledges once done with it (None: not a frame)."""
        self._state = "running"
        self.ready()
        while self.running:
            item = take()
            if item is None:
                if self._ends is not None and self._ended is None:
                    self.end_when_done(inboxes)
                with self._wake:
                    if self.running and not any(inbox.pending() for inbox in inboxes):
                        self._wake.wait(POLL_S)
                continue
            started = time.perf_counter()
            yield item
            self.processed(time.perf_counter() - started, stamp(item))
            if (frame := seq(item)) is not None:
                self.ack(frame)

    def credits(self) -> Credits | None:
        """The credits of a lossless source (None: it sends at its own pace); closed with the node."""
        if not (self.flow.lossless and self.flow.credits_from):
            return None
        credits = Credits(self.session, self.keys, self.flow.credits_from, self.flow.window,
                          lambda note: self.log.info("%s", note))
        self._credits.append(credits)
        return credits

    def ready(self) -> None:
        """Say, once, that the node's inputs are subscribed: what it built to get there is settled (``settle``),
        ``serving`` is set, and an ack of -1 goes out when it acknowledges frames."""
        if not self.serving.is_set():
            self.settle()
        self.serving.set()
        if self.flow.acks and not self._ready:
            self._ready = True
            self.ack(-1)

    def settle(self) -> None:
        """The node's set-up is done (its inputs subscribed, or a source's first frame next): collect once and
        leave every object alive now out of later collections (``memory.settle_heap``). What a node builds as it
        starts (its scene, detectors, compiled kernels) would otherwise stay for the full collections to walk
        again and again, each a pause of tens of milliseconds in the middle of its frames."""
        settle_heap()

    def ack(self, seq: int) -> None:
        """Acknowledge every frame up to ``seq`` as dealt with (only when the flow plan asks for acks)."""
        if self.flow.acks:
            self._acked = FlowAck(header=Header(stamp_ns=time.time_ns()), node=self.name, seq=seq,
                                  started_ns=self._started_ns)
            self._ack_pub.put(self._acked)

    def published_counts(self) -> dict[str, int]:
        """Messages put so far on each output key."""
        return {publisher.key: publisher.counter.messages for publisher in self._publishers}

    def end_of_stream(self, last_seq: int, frames: int) -> None:
        """A source's end: it sent ``frames`` frames, the last numbered ``last_seq`` (-1: none)."""
        self._publish_end(end_message(self.name, last_seq, self.published_counts(), frames))

    def end_when_done(self, inputs: Sequence[Tapped] = ()) -> bool:
        """Publish the node's end if every upstream node has ended and what they published on keys that
        ``inputs`` (its inboxes, or subscriptions it serves itself) take in has arrived; messages still
        missing after ``END_GRACE_S`` without any arrival are given up on, frames counted as missing.
        The caller has dealt with everything that arrived. True once the node has ended."""
        if self._ended is not None:
            return True
        if self._ends is None or not self._ends.all_ended():
            return False
        received: dict[str, int] = {}
        for tapped in inputs:
            for key, count in tapped.counter.counts_by_key().items():
                received[key] = received.get(key, 0) + count
        expressions = [zenoh.KeyExpr(tapped.key) for tapped in inputs]
        expected = {key: count for key, count in self._ends.published().items()
                    if any(e.includes(zenoh.KeyExpr(key)) for e in expressions)}
        short = {key: count - received.get(key, 0) for key, count in expected.items() if count > received.get(key, 0)}
        if short:
            now, total = time.monotonic(), sum(received.get(key, 0) for key in expected)
            if self._short_since is None or total != self._short_total:
                self._short_since, self._short_total = now, total
                return False
            if now - self._short_since < END_GRACE_S:
                return False
            self.log.warning("ending without %d message(s) upstream published: %s", sum(short.values()),
                             ", ".join(f"{key} ({count})" for key, count in sorted(short.items())))
        last = self._ends.last_seq()
        for tapped in inputs:
            tapped.count_tail(last)
        self._publish_end(end_message(self.name, last, self.published_counts()))
        return True

    def _publish_end(self, end: FlowEnd) -> None:
        """Publish ``end``, just after the statistics it closes (a recorder that ends on it has them) and after
        every send the process's outbox holds (the end goes straight to the bus: it must not leave before the
        last frames it counts, queued there while a node of this process took them)."""
        self.host.local.outbox.flush()
        self._ended = end
        self._last_stats_pub.put(self.stats())
        self._end_pub.put(end)
        self.log.info("end of stream: last frame %d%s", end.last_seq,
                      f", {end.frames} frames sent" if end.frames else "")

    def _on_ack_query(self, query: zenoh.Query) -> None:
        if self._acked is not None:
            query.reply(self.keys.ack(self.name), encode(self._acked))

    def _on_end_query(self, query: zenoh.Query) -> None:
        if self._ended is not None:
            query.reply(self.keys.end(self.name), encode(self._ended))

    def linger(self, seconds: float = LINGER_S) -> None:
        """Stay up a moment after a job's last message while anyone subscribes to an output.

        Large payloads travel between local processes through the sender's shared memory;
        a sender that exits at once can take its last messages with it.
        """
        if any(publisher.matched() for publisher in self._publishers):
            self.wait(seconds)

    def processed(self, seconds: float, stamp_ns: int | None = None) -> None:
        """Count one processed input that took ``seconds`` (sources call this per frame); with its
        ``stamp_ns``, its age now counts as the node's latency (``AgeWindow`` says which ages count)."""
        self._state = "running"
        self._processed += 1
        self._processing.add(seconds)
        if stamp_ns is not None:
            self._ages.add_stamp(stamp_ns)

    def report(self, kind: str, detail: str, key: str = "", count: int = 1) -> None:
        """Count ``count`` skipped inputs; log and publish an ErrorReport at most once a second per kind and key."""
        slot = (kind, key)
        count = self._errors.get(slot, 0) + count
        self._errors[slot] = count
        now = time.monotonic()
        if now - self._last_report.get(slot, -REPORT_EVERY_S) < REPORT_EVERY_S:
            return
        self._last_report[slot] = now
        self.log.warning("%s on %s (%d so far): %s", kind, key or "-", count, detail)
        self._errors_pub.put(ErrorReport(header=Header(stamp_ns=time.time_ns()), node=self.name,
                                         kind=kind, detail=detail, key=key, count=count))

    def skipped(self) -> dict[str, int]:
        """Inputs skipped so far, by the kind given to ``report``."""
        totals: dict[str, int] = {}
        for (kind, _), count in list(self._errors.items()):
            totals[kind] = totals.get(kind, 0) + count
        return totals

    def _on_decode_error(self, key: str, error: DecodeError) -> None:
        self.report("decode_error", str(error), key)

    def stats(self) -> NodeStats:
        """The node's health now."""
        tracked = [counter.snapshot() for counter in self._tracked]
        inputs = [inbox.counter.snapshot() for inbox in self._inboxes] + [s for s in tracked if s.direction == "in"]
        outputs = [pub.counter.snapshot() for pub in self._publishers] + [s for s in tracked if s.direction == "out"]
        p50, p99 = self._processing.percentiles_ms(50, 99)
        age_p50, age_p99 = self._ages.percentiles_ms(50, 99)
        synced = tuple(group.stats() for group in self._syncs)
        self._stats_seq += 1
        return NodeStats(
            header=Header(stamp_ns=time.time_ns(), seq=self._stats_seq),
            node=self.name, kind=self.kind, host=socket.gethostname(), pid=os.getpid(),
            state=self._state if self.running else "stopping",
            uptime_s=time.monotonic() - self._started,
            received=sum(s.messages for s in inputs), published=sum(s.messages for s in outputs),
            processed=self._processed, dropped=sum(s.dropped for s in inputs) + sum(group.dropped for group in synced),
            missing=sum(s.missing for s in inputs), decode_errors=sum(s.decode_errors for s in inputs),
            ended=self._ended is not None,
            processing_ms_p50=p50, processing_ms_p99=p99, latency_ms_p50=age_p50, latency_ms_p99=age_p99,
            skipped=self.skipped(),
            streams=tuple(inputs + outputs),
            synced=synced,
        )

    def _stats_loop(self) -> None:
        while not self._stop.wait(self._stats_period_s):
            self._publish_stats()
            self._yield_to_an_elder()

    def _yield_to_an_elder(self) -> None:
        """Stop with ``taken`` set when another process answers for this node's name on the rig and
        started first (ties: the lower host, pid).

        The check before the token is declared can miss a holder whose token has not reached this
        session yet (a loaded machine, two nodes starting at once); both answer on the state key,
        so the younger of two sees the elder here within a stats period and leaves."""
        mine = (time.time_ns() - int((time.monotonic() - self._started) * 1e9), socket.gethostname(), os.getpid())
        try:
            others = [stats for _, stats in every_answer(self.session, self.keys.state(self.name), NodeStats,
                                                         NAME_QUERY_S)]
        except zenoh.ZError:  # the session is closing under us
            return
        for other in others:
            theirs = (other.header.stamp_ns - int(other.uptime_s * 1e9), other.host, other.pid)
            if theirs[1:] != mine[1:] and theirs < mine:
                self.taken = _taken_message(self.name, self.keys, [other], "stopping this later one")
                self.stop()
                return

    def _publish_stats(self) -> None:
        try:
            self._stats_pub.put(self.stats())
        except zenoh.ZError as exc:  # the session is closing under us
            self.log.debug("stats not published: %s", exc)

    def _on_state_query(self, query: zenoh.Query) -> None:
        query.reply(self.keys.state(self.name), encode(self.stats()))

    def close(self) -> None:
        """Stop, undeclare everything and close the session (well within 2 s)."""
        self.stop()
        self._stats_thread.join(timeout=1.0)
        self._publish_stats()  # the last counts, for whoever sums a run up after this node has gone
        self.host.local.outbox.flush()
        if self._ends is not None:
            self._ends.close()
        for credits in self._credits:
            credits.close()
        for entity in [*self._inboxes, *self._publishers, self._stats_pub, self._errors_pub, self._ack_pub,
                       self._end_pub, self._last_stats_pub]:
            entity.close()
        for queryable in [*self._answers, self._queryable, self._end_answer, self._ack_answer]:
            queryable.undeclare()
        self._token.undeclare()
        self._close_host()

    def _close_host(self) -> None:
        """Close the session when this node opened it (nodes of a group share their process's)."""
        if self._owns_host:
            self.host.close()


class Synced(Generic[M]):
    """Sets of one message per named input, joined on their headers (made by ``Node.synced``).

    Iterating yields ``{name: message}`` until the node stops. ``take`` moves what the inboxes
    hold into the join and returns the oldest complete set waiting, or None.
    """

    def __init__(self, node: Node, inboxes: dict[str, Inbox], joiner: Joiner[M], by: JoinBy, latest: bool):
        self.inboxes = inboxes
        self.joiner = joiner
        self.by = by
        self.latest = latest
        self._node = node
        self._lock = threading.Lock()

    def __iter__(self) -> Iterator[dict[str, M]]:
        reference = self.joiner.reference
        return self._node._serve(self.take, list(self.inboxes.values()), lambda s: s[reference].header.stamp_ns,
                                 lambda s: s[reference].header.seq)

    def take(self) -> dict[str, M] | None:
        """Move queued messages into the join, one per input in turn (all of them when latest-wins,
        else until a set is complete); the oldest complete set waiting, or None."""
        with self._lock:
            while self.latest or not self.joiner.ready():
                moved = 0
                for name, inbox in self.inboxes.items():
                    received = inbox.take()
                    if received is not None:
                        moved += 1
                        self.joiner.push(name, join_key(received.message.header, self.by), received.message)
                if not moved:
                    break
            joined = self.joiner.pop()
        return None if joined is None else joined[1]

    def stats(self) -> SyncStats:
        with self._lock:
            joiner = self.joiner
            inputs = tuple(SyncInputStats(name=name, key=inbox.key, **asdict(joiner.counts(name)))
                           for name, inbox in self.inboxes.items())
            return SyncStats(by=self.by, tolerance_ns=joiner.tolerance, sets=joiner.sets, dropped=joiner.dropped,
                             resets=joiner.resets, inputs=inputs)


def run_node(name: str, kind: str, bus: BusConfig, body: Callable[[Node], object],
             flow: FlowPlan | None = None) -> int:
    """Run ``body`` as node ``name`` until it returns or SIGINT/SIGTERM arrives; return an exit code
    (``serve``'s)."""
    log = logging.getLogger(f"artrack.{kind}")
    stopper = Stopper()
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, stopper)
    try:
        node = Node(name, kind, bus, flow=flow)
    except (BusError, NameTaken) as exc:
        log.error("%s", exc)
        return EXIT_CANNOT_RUN
    with node:
        stopper.add(node)
        settle_heap()
        return serve(node, body)


class Stoppable(Protocol):
    """What a ``Stopper`` stops: a node."""

    def stop(self) -> None: ...


class Stopper:
    """The SIGINT/SIGTERM handler of a process's nodes, installed before they are made: a node is live on the bus
    from its construction on, so a signal may come before it runs; a node added after a signal stops at once."""

    def __init__(self) -> None:
        self.asked = threading.Event()
        self.nodes: list[Stoppable] = []

    def __call__(self, *_: object) -> None:
        self.asked.set()
        for node in list(self.nodes):
            node.stop()

    def add(self, node: Stoppable) -> None:
        """Stop ``node`` with the others when a signal comes, or now if one came."""
        self.nodes.append(node)
        if self.asked.is_set():
            node.stop()


def serve(node: Node, body: Callable[[Node], object]) -> int:
    """Run ``body`` on ``node`` (up, not yet closed) and say how it went, as an exit code: 2
    (``EXIT_CANNOT_RUN``) for a ``NodeError`` or a name another process holds, 1 for any other
    exception, else the code ``body`` returned (a replay's 3 for a damaged file), 0 for none."""
    log = node.log
    log.info("node %s (%s) up on %s, pid %d", node.name, node.kind, node.keys.prefix, os.getpid())
    try:
        returned = body(node)
    except NodeError as exc:
        node.failure = f"node {node.name}: {exc}"
        log.error("%s", node.failure)
        return EXIT_CANNOT_RUN
    except Exception as exc:
        node.failure = f"node {node.name} failed: {type(exc).__name__}: {exc}"
        log.exception("node %s failed", node.name)
        return 1
    if node.running:
        node.linger()
    if node.taken is not None:
        node.failure = node.taken
        log.error("%s", node.taken)
        return EXIT_CANNOT_RUN
    log.info("node %s stopped", node.name)
    return returned if isinstance(returned, int) else 0
