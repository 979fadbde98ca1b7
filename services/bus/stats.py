"""Counters and timing windows behind every node's ``NodeStats``."""

from __future__ import annotations

import threading
import time
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from protocol.system import LATENCY_AGE_MAX_S, StreamStats


@dataclass
class StreamCounter:
    """Thread-safe counts for one subscribed or published key expression.

    ``by_key`` counts the messages of each concrete key it matched (given to ``count``);
    ``missing`` the frames that never arrived (see ``SeqGaps``).
    """

    key: str
    direction: str
    messages: int = 0
    dropped: int = 0
    missing: int = 0
    decode_errors: int = 0
    by_key: dict[str, int] = field(default_factory=dict, repr=False)
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)
    _rate: RateMeter = field(default_factory=lambda: RateMeter(), repr=False)

    def count(self, *, messages: int = 0, dropped: int = 0, decode_errors: int = 0, missing: int = 0,
              key: str | None = None) -> None:
        with self._lock:
            self.messages += messages
            self.dropped += dropped
            self.missing += missing
            self.decode_errors += decode_errors
            if messages:
                self._rate.tick(messages)
                if key is not None:
                    self.by_key[key] = self.by_key.get(key, 0) + messages

    def counts_by_key(self) -> dict[str, int]:
        with self._lock:
            return dict(self.by_key)

    def snapshot(self) -> StreamStats:
        with self._lock:
            return StreamStats(key=self.key, direction=self.direction, messages=self.messages,
                               dropped=self.dropped, missing=self.missing, decode_errors=self.decode_errors,
                               rate_hz=self._rate.rate())


class SeqGaps:
    """Frames missing from streams of frames, told by their ``header.seq`` (not thread-safe).

    Frames of one key carry increasing seqs; ``note`` returns how many were skipped before the
    one just seen. A seq at or below the last one seen is a source that started over (a loop,
    a restart): counting begins again from it. ``tail(last_seq)`` counts those never seen after
    the last one received, once the source has said its last seq.
    """

    def __init__(self) -> None:
        self._last: dict[str, int] = {}

    def note(self, key: str, seq: int) -> int:
        last = self._last.get(key)
        self._last[key] = seq
        return seq - last - 1 if last is not None and seq > last + 1 else 0

    def tail(self, last_seq: int) -> int:
        """Frames after the last one received, up to ``last_seq``, summed over the keys seen."""
        return sum(max(0, last_seq - last) for last in self._last.values())


class RateMeter:
    """Events per second over a sliding window of ``window_s`` seconds (not thread-safe)."""

    def __init__(self, window_s: float = 2.0):
        self.window_s = window_s
        self._events: deque[tuple[float, int]] = deque()

    def tick(self, n: int = 1) -> None:
        now = time.monotonic()
        self._events.append((now, n))
        self._trim(now)

    def rate(self) -> float:
        now = time.monotonic()
        self._trim(now)
        return sum(n for _, n in self._events) / self.window_s

    def _trim(self, now: float) -> None:
        while self._events and now - self._events[0][0] > self.window_s:
            self._events.popleft()


class LatencyWindow:
    """The last ``size`` durations (seconds), with percentiles in milliseconds. Thread-safe."""

    def __init__(self, size: int = 1000):
        self._values: deque[float] = deque(maxlen=size)
        self._lock = threading.Lock()

    def add(self, seconds: float) -> None:
        with self._lock:
            self._values.append(seconds)

    def __len__(self) -> int:
        return len(self._values)

    def percentiles_ms(self, *qs: float) -> tuple[float | None, ...]:
        with self._lock:
            if not self._values:
                return tuple(None for _ in qs)
            values = np.fromiter(self._values, dtype=np.float64) * 1e3
        return tuple(float(v) for v in np.percentile(values, qs))


class AgeWindow(LatencyWindow):
    """The ages of the last ``size`` inputs when they were done with (now - their header stamp, on
    CLOCK_REALTIME), counting only ages from 0 to ``max_s``: a stamp from another clock (a replay
    stamped with the recording's time, a host out of sync) gives no figure rather than a wrong one."""

    def __init__(self, max_s: float = LATENCY_AGE_MAX_S, size: int = 1000):
        super().__init__(size)
        self.max_s = max_s

    def add_stamp(self, stamp_ns: int, now_ns: int | None = None) -> bool:
        """Count the age of an input stamped ``stamp_ns`` at ``now_ns`` (default: now); False when out of range."""
        age = ((time.time_ns() if now_ns is None else now_ns) - stamp_ns) / 1e9
        if not 0.0 <= age <= self.max_s:
            return False
        self.add(age)
        return True
