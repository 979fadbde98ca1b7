"""Replay timing: when each recorded message is due, and pause, resume and step.

Messages carry log times (their arrival at the recorder, ns). A pass plays them in file
order against a *position* on the recording's time line (ns since the file's first message):
while playing, the position advances ``rate`` ns per ns of this process's monotonic clock;
while paused it stands still. A message is due when the position reaches its log time; the
first message of a pass plays at once. ``step`` releases the next message at once and
leaves playback paused at that message; ``resume`` goes on from the position, so the gaps
that follow keep their recorded lengths (divided by ``rate``).
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from mcap.records import Channel

from services.recorder.reading import Damage, Recorded, Scan

SLICE_S = 0.1
"""Longest uninterrupted wait, so that ``running()`` turning false is noticed promptly."""
LATENESS_KEPT = 100_000
"""Lateness figures are over the last this many publications."""


class Pacer:
    """The position on the recording's time line, and the commands that move it. Thread-safe.

    ``running`` is polled while waiting (a node's ``running``); ``clock`` returns ns.
    """

    def __init__(self, rate: float, *, paused: bool = False, running: Callable[[], bool] = lambda: True,
                 clock: Callable[[], int] = time.monotonic_ns):
        if rate <= 0:
            raise ValueError(f"rate must be positive, got {rate}")
        self.rate = rate
        self._running = running
        self._clock = clock
        self._changed = threading.Condition()
        self._paused = paused
        self._stopped = False
        self._steps = 0
        self._media_ns = 0  # the position at wall time _wall_ns (while playing) or now (while paused)
        self._wall_ns = clock()

    @property
    def state(self) -> str:
        """``playing``, ``paused`` or ``stopped``."""
        return "stopped" if self._stopped else "paused" if self._paused else "playing"

    def position_ns(self) -> int:
        with self._changed:
            return self._position(self._clock())

    def _position(self, now: int) -> int:
        return self._media_ns if self._paused else self._media_ns + round((now - self._wall_ns) * self.rate)

    def anchor(self, media_ns: int) -> None:
        """Make ``media_ns`` the position now (the start of a pass)."""
        with self._changed:
            self._media_ns, self._wall_ns = media_ns, self._clock()

    def pause(self) -> None:
        with self._changed:
            if not self._paused:
                self._media_ns, self._paused = self._position(self._clock()), True

    def resume(self) -> None:
        with self._changed:
            if self._paused:
                self._wall_ns, self._paused = self._clock(), False
                self._changed.notify_all()

    def step(self) -> None:
        """Release the next message now; pause (or stay paused) after it."""
        with self._changed:
            if not self._paused:
                self._media_ns, self._paused = self._position(self._clock()), True
            self._steps += 1
            self._changed.notify_all()

    def stop(self) -> None:
        with self._changed:
            self._stopped = True
            self._changed.notify_all()

    def wait_for(self, media_ns: int) -> int | None:
        """Block until the message at ``media_ns`` is due; the clock time it was due (ns), or
        None when stopped first. A step makes it due at once and moves the position there."""
        with self._changed:
            while True:
                if self._stopped or not self._running():
                    self._stopped = True
                    return None
                now = self._clock()
                if self._steps:
                    self._steps -= 1
                    self._media_ns = media_ns
                    return now
                if self._paused:
                    self._changed.wait(SLICE_S)
                    continue
                due = self._wall_ns + round((media_ns - self._media_ns) / self.rate)
                if now >= due:
                    return due
                self._changed.wait(min((due - now) / 1e9, SLICE_S))


@dataclass(frozen=True)
class Window:
    """Which part of the recording to play, in ns from its first message (end None: to the end)."""

    start_ns: int = 0
    end_ns: int | None = None


@dataclass
class Pass:
    """What one pass over a file did.

    ``read``: intact messages read (selected or not); ``last_ns``: position of the last of
    them; ``lateness_ns``: clock time each publication began minus the time it was due (the
    last ``LATENESS_KEPT``);
    ``damage``: where the file's intact part ended, when the pass got there; ``stopped``: the
    pacer was stopped (or the node stopped running) before the pass ended.
    """

    played: int = 0
    read: int = 0
    last_ns: int = 0
    lateness_ns: deque[int] = field(default_factory=lambda: deque(maxlen=LATENESS_KEPT))
    damage: Damage | None = None
    stopped: bool = False


def play_pass(path: Path | str, pacer: Pacer, publish: Callable[[Recorded], None], *,
              select: Callable[[Channel], bool] = lambda channel: True, window: Window = Window(),
              prepare: Callable[[Recorded], None] = lambda recorded: None,
              clock: Callable[[], int] = time.monotonic_ns) -> Pass:
    """Play ``path`` once, in file order: ``publish`` each selected message inside ``window`` when due.

    ``prepare`` sees each message before the wait for it (to declare its publisher in time);
    lateness is measured as ``publish`` is called.
    """
    scan = Scan(path)
    done = Pass()
    first: int | None = None
    for recorded in scan.messages():
        if first is None:
            first = recorded.message.log_time
        position = recorded.message.log_time - first
        done.read += 1
        done.last_ns = position
        if window.end_ns is not None and position > window.end_ns:
            return done
        if position < window.start_ns or not select(recorded.channel):
            continue
        prepare(recorded)
        if done.played == 0:
            pacer.anchor(position)
        due = pacer.wait_for(position)
        if due is None:
            done.stopped = True
            return done
        done.lateness_ns.append(clock() - due)
        publish(recorded)
        done.played += 1
    done.damage = scan.damage
    return done
