"""Stamps of the frames of a source that is not a camera (a file, a folder, a scene, a recording): the
source's own clock, started at the wall-clock time of its first frame.

Such a frame stands for an instant of the source's own time, whenever it goes out: in a lossless run
(``services.runtime.flow``) frames wait for the slowest node that takes them, and in a real-time run for a
busy machine, so the time a frame goes out tells how busy the machine was, not the instant its content
shows. ``SourceClock`` stamps the first frame with the wall-clock time it goes out and each later one a
frame interval after the one before: the pace asked, else the difference of the two frames' own times,
else ``NOMINAL_S``. A frame that goes out late keeps its place on that clock, so what nodes derive from
stamps (a camera's velocity, a keyframe's age, a body's predicted pose, a filter's rate) does not follow
the load, and the latency a node measures from a stamp includes the time the frame came late, as it would
from a camera's. The stamps fall behind the wall clock while the source or the pipeline is slower than the
pace, and may run ahead of it when frames go out faster than their own time (``fps`` 0): nodes count an
input's age as latency only from 0 to ``protocol.system.LATENCY_AGE_MAX_S``, so neither gives a wrong
latency. A camera's frames are stamped by the wall clock as they are taken.
"""

from __future__ import annotations

import time

NOMINAL_S = 1.0 / 30.0
"""The interval after a frame that has no own time, or whose own time is not after the last frame's
(a source started over)."""


class SourceClock:
    """Stamps (int ns) of one source's frames, one ``stamp`` call per frame in the order they go out."""

    def __init__(self) -> None:
        self._last_stamp_ns: int | None = None
        self._last_own_ns: int | None = None

    def stamp(self, own_ns: int | None, interval_s: float | None = None) -> int:
        """The next frame's stamp: the wall clock now for the first frame; then the last stamp plus
        ``interval_s`` (the pace asked), else plus ``own_ns`` (the frame's own time, ns) minus the last
        frame's own time when both are known and it is later, else plus ``NOMINAL_S``."""
        last, last_own = self._last_stamp_ns, self._last_own_ns
        if last is None:
            stamp = time.time_ns()
        elif interval_s is not None and interval_s > 0:
            stamp = last + round(interval_s * 1e9)
        elif own_ns is not None and last_own is not None and own_ns > last_own:
            stamp = last + own_ns - last_own
        else:
            stamp = last + round(NOMINAL_S * 1e9)
        self._last_stamp_ns, self._last_own_ns = stamp, own_ns
        return stamp
