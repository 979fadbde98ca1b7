"""Joining one message from each of several inputs: the logic behind ``Node.synced``.

A ``Joiner`` holds the messages of N named inputs that are waiting for partners and emits
complete sets, one message per input, in increasing order of the set's key. The key is a
message's header ``seq`` (joined when equal) or its ``stamp_ns`` (joined within a
tolerance): a set forms around a message of the *reference* input (the first name) when
every other input has a pending message with ``|key - key_ref| <= tolerance``; of several,
the nearest is taken (ties: the older). A set goes out as soon as it is complete, without
waiting to see whether a nearer partner arrives later, so the tolerance should stay below
half the input period; then at most one message of each input can match.

Memory is bounded: each input keeps at most ``depth`` pending messages (beyond that the
oldest is evicted), and at most ``ready`` complete sets wait to be taken (beyond that the
oldest set is dropped: ``ready=1`` is latest-wins, as frames are). Nothing leaves unseen;
every message that does not end up in a set is counted on its input as

* ``evicted``: pushed out of a full pending buffer while still waiting for partners;
* ``superseded``: left waiting when a newer set was emitted (sets go out in key order, so
  it can no longer be joined);
* ``out_of_order``: arrived already too old to join anything newer than the last set
  emitted, or repeating a key that is still pending on its input.

``depth`` consecutive out-of-order arrivals on one input mean its source started over (a
restarted capture counting ``seq`` from 0, a replay looping): the joiner then forgets the
last set's key, so the new run can be joined, and counts a ``reset``.

This module is pure bookkeeping: no bus, no clock.
"""

from __future__ import annotations

import bisect
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Generic, Literal, Protocol, TypeVar

T = TypeVar("T")

JoinBy = Literal["seq", "stamp"]

__all__ = ["InputCounts", "JoinBy", "Joiner", "join_key", "key_tolerance"]


class Stamped(Protocol):
    """What a key is read from: a message header."""

    stamp_ns: int
    seq: int


def join_key(header: Stamped, by: JoinBy) -> int:
    """The key a message joins on: its header's ``seq`` or ``stamp_ns``."""
    return header.seq if by == "seq" else header.stamp_ns


def key_tolerance(by: JoinBy, tolerance_s: float) -> int:
    """The tolerance in key units (ns for ``stamp``; 0 for ``seq``) after checking ``by`` and ``tolerance_s``."""
    if by not in ("seq", "stamp"):
        raise ValueError(f"by must be 'seq' or 'stamp', not {by!r}")
    if not 0 <= tolerance_s < float("inf"):
        raise ValueError(f"tolerance_s must be a finite number of seconds >= 0, got {tolerance_s}")
    if by == "seq" and tolerance_s:
        raise ValueError(f"tolerance_s={tolerance_s} applies to by='stamp' only: sequence numbers join when equal")
    return round(tolerance_s * 1e9)


@dataclass
class InputCounts:
    """What became of the messages pushed on one input."""

    received: int = 0
    joined: int = 0
    evicted: int = 0
    superseded: int = 0
    out_of_order: int = 0

    @property
    def unjoined(self) -> int:
        return self.evicted + self.superseded + self.out_of_order


@dataclass
class _Pending(Generic[T]):
    """One input's waiting messages as ``(key, arrival, item)``, sorted by key then arrival."""

    entries: list[tuple[int, int, T]] = field(default_factory=list)
    counts: InputCounts = field(default_factory=InputCounts)
    late_run: int = 0

    def keys(self) -> list[int]:
        return [entry[0] for entry in self.entries]


class Joiner(Generic[T]):
    """Complete sets of one item per name, joined by an int key (see the module docstring).

    ``names``: the inputs, the first being the reference whose key a set carries;
    ``tolerance``: the largest ``|key - key_ref|`` that still joins (key units, >= 0);
    ``depth``: pending items kept per input (>= 1); ``ready``: complete sets kept waiting
    to be taken (>= 1).
    """

    def __init__(self, names: Sequence[str], *, tolerance: int = 0, depth: int = 8, ready: int = 1):
        names = tuple(names)
        if len(names) < 2:
            raise ValueError(f"a join needs at least two inputs, got {list(names)}")
        if len(set(names)) != len(names):
            raise ValueError(f"input names must differ, got {list(names)}")
        if tolerance < 0:
            raise ValueError(f"tolerance must be >= 0, got {tolerance}")
        if depth < 1 or ready < 1:
            raise ValueError(f"depth and ready must be >= 1, got depth={depth}, ready={ready}")
        self.names = names
        self.reference = names[0]
        self.tolerance = tolerance
        self.depth = depth
        self._pending: dict[str, _Pending[T]] = {name: _Pending() for name in names}
        self._ready: deque[tuple[int, dict[str, T]]] = deque(maxlen=ready)
        self._arrivals = 0
        self.last_key: int | None = None
        """The key of the newest set emitted (None before the first, and after a reset)."""
        self.sets = 0
        """Complete sets formed."""
        self.dropped = 0
        """Complete sets dropped unseen because ``ready`` newer ones were waiting."""
        self.resets = 0
        """Times an input started over (see the module docstring)."""

    def counts(self, name: str) -> InputCounts:
        """The counts of input ``name`` (live: they keep changing)."""
        return self._pending[name].counts

    def pending(self, name: str) -> int:
        """Items of ``name`` waiting for partners."""
        return len(self._pending[name].entries)

    def ready(self) -> int:
        """Complete sets waiting to be taken."""
        return len(self._ready)

    def push(self, name: str, key: int, item: T) -> None:
        """Add ``item`` of input ``name`` with ``key``; emit every set this completes."""
        if name not in self._pending:
            raise KeyError(f"unknown input {name!r}; inputs are {list(self.names)}")
        pending = self._pending[name]
        pending.counts.received += 1
        keys = pending.keys()
        if self._too_old(name, key) or key in keys:
            pending.late_run += 1
            if pending.late_run < self.depth or key in keys:
                pending.counts.out_of_order += 1
                return
            self._reset()
        pending.late_run = 0
        self._arrivals += 1
        bisect.insort(pending.entries, (key, self._arrivals, item), key=lambda entry: entry[:2])
        if len(pending.entries) > self.depth:
            pending.entries.pop(0)
            pending.counts.evicted += 1
        self._emit_complete()

    def pop(self) -> tuple[int, dict[str, T]] | None:
        """The oldest complete set waiting as ``(key of the reference, {name: item})``; None when none is."""
        return self._ready.popleft() if self._ready else None

    def _too_old(self, name: str, key: int) -> bool:
        """True when an item of ``name`` with ``key`` cannot join any set newer than the last one."""
        if self.last_key is None:
            return False
        return key <= self.last_key - (0 if name == self.reference else self.tolerance)

    def _reset(self) -> None:
        self.last_key = None
        self.resets += 1
        for pending in self._pending.values():
            pending.late_run = 0

    def _emit_complete(self) -> None:
        reference = self._pending[self.reference]
        i = 0
        while i < len(reference.entries):
            key = reference.entries[i][0]
            found = {name: self._nearest(name, key) for name in self.names[1:]}
            picks = {name: pick for name, pick in found.items() if pick is not None}
            if len(picks) < len(found):
                i += 1
                continue
            items = {self.reference: reference.entries.pop(i)[2]}
            for name, pick in picks.items():
                items[name] = self._pending[name].entries.pop(pick)[2]
            self._emitted(key, items)
            i = 0

    def _nearest(self, name: str, key: int) -> int | None:
        """Index of the pending item of ``name`` nearest to ``key`` within the tolerance, or None."""
        best, best_distance = None, self.tolerance + 1
        for index, (other, _, _) in enumerate(self._pending[name].entries):
            distance = abs(other - key)
            if distance < best_distance:
                best, best_distance = index, distance
        return best

    def _emitted(self, key: int, items: dict[str, T]) -> None:
        self.last_key = key
        self.sets += 1
        for name in self.names:
            pending = self._pending[name]
            pending.counts.joined += 1
            stale = sum(1 for entry in pending.entries if self._too_old(name, entry[0]))
            del pending.entries[:stale]
            pending.counts.superseded += stale
        if len(self._ready) == self._ready.maxlen:
            self.dropped += 1
        self._ready.append((key, items))
