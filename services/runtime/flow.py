"""Flow control on the bus: credits for lossless sources, ends of stream for an exact end.

The launcher gives each node a ``FlowPlan``. A lossless source sends frame ``N + window`` only once
every node named in ``credits_from`` has acknowledged frame ``N`` (``Credits``); each of those
nodes acknowledges every frame it takes (``FlowAck`` on ``node/<name>/ack``, published by
``Node``). Nodes fed by other nodes' results need no credits: results queue in order and are never
dropped. Every source publishes a ``FlowEnd`` with its last ``seq`` when it runs out of frames;
every other node publishes its own once it holds the ends of all of its ``upstream`` nodes, has
received as many messages on each key as they say they published (an end may overtake data sent
at another priority) and has dealt with them (``Ends``).

A node that dies is no longer waited for (its liveliness token goes); one that comes back announces
itself with an ack of -1 and a new ``started_ns``, and is taken as caught up with what was sent
while it was down.
"""

from __future__ import annotations

import bisect
import threading
import time
from collections.abc import Callable, Iterable

import zenoh
from pydantic import BaseModel, ConfigDict, Field

from protocol.flow import FlowAck, FlowEnd
from protocol.keys import Keys
from protocol.message import Header
from services.bus.discovery import every_answer
from services.bus.pubsub import Listener

END_QUERY_S = 0.5
"""How long a starting node asks the nodes it depends on for their acks or ends so far."""
WAIT_NOTE_S = 5.0
"""A source held back this long by one node says so (then again every this long)."""
DEFAULT_WINDOW = 4


class FlowPlan(BaseModel):
    """A node's part in its pipeline's flow control, set by the launcher (the default: none).

    ``lossless``: frame inputs queue every frame instead of keeping the newest, and frame outputs
    block rather than drop when the bus is congested. ``window``: frames a source may send ahead
    of the slowest of ``credits_from``. ``acks``: the node acknowledges each frame it takes.
    ``upstream``: the nodes whose ends this node waits for before it ends.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    lossless: bool = False
    window: int = Field(default=DEFAULT_WINDOW, ge=1, le=10_000)
    credits_from: tuple[str, ...] = ()
    acks: bool = False
    upstream: tuple[str, ...] = ()


class Credits:
    """The credits of a lossless source: how far ahead of the nodes ``names`` it may send.

    ``wait_for(seq)`` blocks until frame ``seq`` may go (every live node of ``names`` has at most
    ``window - 1`` sent frames it has not acknowledged); ``sent(seq)`` records that it went.
    Frame numbers must increase; one that does not (a source starting over) forgets what was sent.
    """

    def __init__(self, session: zenoh.Session, keys: Keys, names: Iterable[str], window: int,
                 note: Callable[[str], None] | None = None):
        self.window = window
        self._names = tuple(names)
        self._note = note
        self._cond = threading.Condition()
        self._acked: dict[str, int] = {}
        self._runs: dict[str, int] = {}
        self._gone: set[str] = set()
        self._sent: list[int] = []
        self._stopped = False
        self._acks = [Listener(session, keys.ack(name), FlowAck, lambda received: self._take(received.message))
                      for name in self._names]
        self._tokens = [session.liveliness().declare_subscriber(keys.node(name), self._on_token)
                        for name in self._names]
        self.waited_s = 0.0
        for _, ack in every_answer(session, keys.every_node("ack"), FlowAck, END_QUERY_S):
            self._take(ack)

    def _take(self, ack: FlowAck) -> None:
        if ack.node not in self._names:
            return
        with self._cond:
            name = ack.node
            if name not in self._runs:
                self._acked[name] = ack.seq
            elif self._runs[name] != ack.started_ns:  # a new run of the node: caught up with what was sent
                self._acked[name] = max(ack.seq, self._sent[-1] if self._sent else ack.seq)
            else:
                self._acked[name] = max(self._acked[name], ack.seq)
            self._runs[name] = ack.started_ns
            self._gone.discard(name)
            self._cond.notify_all()

    def _on_token(self, sample: zenoh.Sample) -> None:
        if sample.kind == zenoh.SampleKind.DELETE:
            name = str(sample.key_expr).rsplit("/", 1)[-1]
            with self._cond:
                self._gone.add(name)
                self._cond.notify_all()

    def _ahead(self, name: str) -> int:
        """Frames sent that ``name`` has not acknowledged (caller holds the lock)."""
        acked = self._acked.get(name)
        return len(self._sent) if acked is None else len(self._sent) - bisect.bisect_right(self._sent, acked)

    def _blocking(self) -> list[str]:
        return [name for name in self._names if name not in self._gone
                and (name not in self._runs or self._ahead(name) >= self.window)]

    def wait_for(self, seq: int, running: Callable[[], bool]) -> bool:
        """Block until frame ``seq`` may be sent (True), or ``running()`` turns false or ``stop`` (False)."""
        started = time.monotonic()
        noted = started
        with self._cond:
            if self._sent and seq <= self._sent[-1]:  # the source started over: so do the counts
                self._sent.clear()
                self._acked = dict.fromkeys(self._acked, -1)
            while (blocking := self._blocking()) and running() and not self._stopped:
                self._cond.wait(0.1)
                now = time.monotonic()
                if self._note is not None and now - noted >= WAIT_NOTE_S:
                    noted = now
                    self._note(f"frame {seq} held back {now - started:.0f} s, waiting for {', '.join(blocking)}")
            self._trim()
            ok = not self._blocking()
        self.waited_s += time.monotonic() - started
        return ok

    def sent(self, seq: int) -> None:
        with self._cond:
            self._sent.append(seq)

    def _trim(self) -> None:
        """Forget sent frames every node has acknowledged (caller holds the lock)."""
        live = [self._acked[name] for name in self._names if name not in self._gone and name in self._acked]
        if live and len(live) == len([n for n in self._names if n not in self._gone]):
            del self._sent[:bisect.bisect_right(self._sent, min(live))]

    def stop(self) -> None:
        with self._cond:
            self._stopped = True
            self._cond.notify_all()

    def close(self) -> None:
        self.stop()
        for listener in self._acks:
            listener.close()
        for token in self._tokens:
            token.undeclare()


class Ends:
    """The ends of stream of a node's ``upstream`` nodes, as they are published or answered.

    ``on_end`` is called (on Zenoh's thread) at each new end, so a waiting consumer can wake.
    """

    def __init__(self, session: zenoh.Session, keys: Keys, upstream: Iterable[str],
                 on_end: Callable[[], None] = lambda: None):
        self.upstream = tuple(upstream)
        self._session = session
        self._keys = keys
        self._on_end = on_end
        self._ends: dict[str, FlowEnd] = {}
        self._lock = threading.Lock()
        self._listeners = [Listener(session, keys.end(name), FlowEnd, lambda received: self._take(received.message))
                           for name in self.upstream]
        self.ask()

    def ask(self) -> None:
        """Ask the nodes for the ends they have published (one that came before the subscription, or was lost)."""
        for _, end in every_answer(self._session, self._keys.every_node("end"), FlowEnd, END_QUERY_S):
            self._take(end)

    def _take(self, end: FlowEnd) -> None:
        with self._lock:
            if end.node not in self.upstream or end.node in self._ends:
                return
            self._ends[end.node] = end
        self._on_end()

    def all_ended(self) -> bool:
        return bool(self.upstream) and len(self._ends) == len(self.upstream)

    def waiting(self) -> set[str]:
        """The nodes of ``upstream`` that have not ended yet."""
        with self._lock:
            return set(self.upstream) - set(self._ends)

    def published(self) -> dict[str, int]:
        """Messages the ended upstream nodes say they published, by key (summed over nodes)."""
        totals: dict[str, int] = {}
        with self._lock:
            for end in self._ends.values():
                for key, count in end.published.items():
                    totals[key] = totals.get(key, 0) + count
        return totals

    def last_seq(self) -> int:
        """The last frame any upstream source sent (-1 when none sent any)."""
        with self._lock:
            return max((end.last_seq for end in self._ends.values()), default=-1)

    def close(self) -> None:
        for listener in self._listeners:
            listener.close()


def end_message(node: str, last_seq: int, published: dict[str, int], frames: int = 0) -> FlowEnd:
    return FlowEnd(header=Header(stamp_ns=time.time_ns()), node=node, last_seq=last_seq, frames=frames,
                   published=published)
