"""What ``artrack run`` says while a job runs and when it ends, on standard error.

While it runs, on a terminal: one line redrawn in place every ``REFRESH_S``: the source's
frames sent (of the total, when the source is finite), the rate they go out at, the frames
the nodes dropped and the poses received. Not on a terminal, the same line goes to the log
every ``LOG_EVERY_S`` instead. A source with no end (a camera, a synthetic scene without
``--frames``, a looped file) is announced in one line when the job starts.

At the end: per node, the messages in, processed and out, dropped by the node, missing (frames
that never reached it: gaps in their sequence numbers, or after the last one received once the
source ended), unjoined, decode errors and skipped inputs by reason; per pose target, how many
poses came in each tracking state; the rate the source delivered against the one asked (and how
many frames it sent late); which nodes dropped frames (latest-wins inputs) and how to avoid it;
where the sinks' files went; and, last, whether every frame was accounted for (``losses``).
The figures come from the nodes' own statistics, asked on their state queryables twice a
second and once more before the job stops them, and from the final statistics a node
publishes as it closes (a finite source has gone by the end); poses are counted as
they arrive on the rig's pose keys. Standard output stays free for data.
"""

from __future__ import annotations

import logging
import sys
import threading
import time
from collections import Counter, defaultdict
from dataclasses import dataclass, field
from typing import TextIO

import zenoh

from protocol.codec import DecodeError, decode
from protocol.poses import Pose
from protocol.system import NodeStats
from protocol.tracking_state import TrackingState
from services.bus.discovery import node_states
from services.bus.session import BusConfig
from services.launcher.kinds import kind
from services.launcher.observe import format_table
from services.launcher.pipeline import NodeSpec, PipelineSpec

log = logging.getLogger(__name__)

REFRESH_S = 0.5
LOG_EVERY_S = 10.0
QUERY_S = 0.4
JOIN_S = 10.0
"""How long closing waits for the progress thread to finish its last query (a loaded machine is slow)."""
SLOW_SOURCE = 0.9
"""A source delivering less than this share of the rate asked is called out in the summary."""
BURST_FACTOR = 1.05
"""A rate timed by the poses' arrival above this multiple of the rate asked is a burst, not the source's pace."""


@dataclass(frozen=True)
class Display:
    """Where and what a job says: ``progress`` redraws a line in place (a terminal), ``summary`` at the end."""

    out: TextIO = sys.stderr
    progress: bool = False
    summary: bool = True

    @classmethod
    def choose(cls, progress: str = "auto", quiet: bool = False, out: TextIO | None = None) -> Display:
        """``progress``: ``on``, ``off`` or ``auto`` (on when ``out`` is a terminal); ``quiet``: neither
        progress nor summary."""
        out = sys.stderr if out is None else out
        shown = progress == "on" or (progress == "auto" and out.isatty())
        return cls(out=out, progress=shown and not quiet, summary=not quiet)


def frames_expected(node: NodeSpec) -> int | None:
    """How many frames per camera a source node will send; None when it has no end (or it cannot be told)."""
    declared = kind(node.kind)
    return None if declared.source is None else declared.source.frames(declared.validate(node.params))


def _is_sink(kind_name: str) -> bool:
    try:
        return kind(kind_name).sink is not None
    except ValueError:
        return False


@dataclass
class JobFigures:
    """What a job's nodes said about themselves, and the poses seen; filled from bus callbacks."""

    stats: dict[str, NodeStats] = field(default_factory=dict)
    poses: dict[str, Counter[str]] = field(default_factory=lambda: defaultdict(Counter))
    pose_errors: int = 0
    samples: list[tuple[int, int]] = field(default_factory=list)
    """``(stamp_ns, frames sent)`` of the source, one per new statistics message."""
    frames_posed: list[tuple[int, int]] = field(default_factory=list)
    """``(seq, at_ns)`` of the first and the last source frame a pose came from (by sequence number), ``at_ns``
    when the frame went out (a camera's stamp) or when its first pose came."""

    def posed(self, seq: int, at_ns: int) -> None:
        """Note the frame ``seq`` a pose came from, at ``at_ns``."""
        seen = self.frames_posed
        if seen and seq in (seen[0][0], seen[1][0]):
            return
        if not seen:
            seen += [(seq, at_ns), (seq, at_ns)]
        elif seq < seen[0][0]:
            seen[0] = (seq, at_ns)
        elif seq > seen[1][0]:
            seen[1] = (seq, at_ns)

    def update(self, stats: NodeStats, source: str) -> None:
        """Keep ``stats`` when newer than what is known of its node."""
        known = self.stats.get(stats.node)
        if known is not None and known.header.stamp_ns >= stats.header.stamp_ns:
            return
        self.stats[stats.node] = stats
        if stats.node == source:
            self.samples.append((stats.header.stamp_ns, frames_sent(stats)))


def frames_sent(stats: NodeStats) -> int:
    """Frames a source node sent: the messages on its first camera's image key (0 before any)."""
    return next((s.messages for s in stats.streams if s.direction == "out" and s.key.endswith("/image")), 0)


def delivered_rate(figures: JobFigures, from_poses: bool, asked: float | None = None) -> float | None:
    """Frames per second the source sent, None when it cannot be told.

    ``from_poses`` (a real-time run): from the first and the last frame a pose came from (a tracker
    always gets the last frame: latest-wins keeps the newest), their sequence numbers apart over their
    times apart (``JobFigures.frames_posed``). A source never sends faster than the ``asked`` rate, so a
    figure above it says that the poses reached this process in a burst (its threads held up on a busy
    machine), not how fast the frames went: then, as otherwise (a lossless run, whose frames go out at the
    pace of its slowest node), from the source's statistics: between the first that had frames and the last
    still short of the final count.
    """
    if from_poses and len(figures.frames_posed) == 2:
        (seq0, t0), (seq1, t1) = figures.frames_posed
        rate = (seq1 - seq0) / ((t1 - t0) / 1e9) if seq1 > seq0 and t1 > t0 else None
        if rate is not None and (not asked or rate <= BURST_FACTOR * asked):
            return rate
    samples = figures.samples
    if not samples:
        return None
    final = max(n for _, n in samples)
    inside = [(t, n) for t, n in samples if 0 < n < final]
    if len(inside) < 2 or inside[-1][0] <= inside[0][0]:
        return None
    (t0, n0), (t1, n1) = inside[0], inside[-1]
    return (n1 - n0) / ((t1 - t0) / 1e9)


class JobWatch:
    """Watches one job on ``session``: see the module docstring. ``gather`` before the nodes stop, ``close``
    after (it prints the summary)."""

    def __init__(self, session: zenoh.Session, bus: BusConfig, spec: PipelineSpec, display: Display):
        self.session = session
        self.bus = bus
        self.spec = spec
        self.display = display
        sources = spec.sources()
        self.source = sources[0]
        source = spec.nodes[self.source]
        self.total = frames_expected(source)
        declared = kind(source.kind)
        params = declared.validate(source.params)
        self.asked = declared.source.fps(params) if declared.source is not None else None
        self.lossless = spec.lossless()
        self.wall_stamps = declared.source is not None and declared.source.wall_stamps(params)
        """Whether frames are stamped when taken (a camera): else a frame's first pose is timed as it comes."""
        self.figures = JobFigures()
        self.restarts: dict[str, int] = {}
        """Nodes the job restarted, and how often (set by the job before the summary)."""
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._started = time.monotonic()
        if self.total is None and display.summary:
            self._say(f"live source ({self.source}): runs until Ctrl-C")
        self._subscribers = [
            session.declare_subscriber(bus.keys.poses(), self._on_pose),
            session.declare_subscriber(bus.keys.all_stats(), self._on_stats),
        ]
        self._thread = threading.Thread(target=self._loop, name="job-progress", daemon=True)
        self._thread.start()

    def _say(self, line: str) -> None:
        self.display.out.write(line + "\n")
        self.display.out.flush()

    def _on_pose(self, sample: zenoh.Sample) -> None:
        try:
            message = decode(sample.payload.to_bytes())
            target = self.bus.keys.target(str(sample.key_expr))
        except (DecodeError, ValueError):
            with self._lock:
                self.figures.pose_errors += 1
            return
        if isinstance(message, Pose):
            with self._lock:
                self.figures.poses[target][str(message.state)] += 1
                self.figures.posed(message.header.seq, message.header.stamp_ns if self.wall_stamps else time.time_ns())

    def _on_stats(self, sample: zenoh.Sample) -> None:
        try:
            message = decode(sample.payload.to_bytes())
            rig, _ = self.bus.keys.split_node(str(sample.key_expr))
        except (DecodeError, ValueError):
            return
        if isinstance(message, NodeStats) and rig == self.bus.rig:
            with self._lock:
                self.figures.update(message, self.source)

    def gather(self) -> None:
        """Ask every node of the job for its statistics now (call before they are stopped)."""
        for (rig, _), stats in node_states(self.session, self.bus.keys, QUERY_S).items():
            if rig == self.bus.rig and stats.node in self.spec.nodes:
                with self._lock:
                    self.figures.update(stats, self.source)

    def _loop(self) -> None:
        logged = time.monotonic()
        while not self._stop.wait(REFRESH_S):
            self.gather()
            line = self.progress_line()
            if self.display.progress:  # the cursor goes back to the start: a node's log line overwrites it
                self.display.out.write("\x1b[K" + line + "\r")
                self.display.out.flush()
            elif time.monotonic() - logged >= LOG_EVERY_S:
                log.info("%s", line)
                logged = time.monotonic()

    def progress_line(self) -> str:
        """One line: frames sent (of the total), their rate, drops and poses so far."""
        with self._lock:
            stats = dict(self.figures.stats)
            samples = list(self.figures.samples[-3:])
            poses = sum(sum(c.values()) for c in self.figures.poses.values())
        source = stats.get(self.source)
        sent = frames_sent(source) if source is not None else 0
        parts = [f"frames {sent}/{self.total}" if self.total else f"frames {sent}"]
        if len(samples) >= 2 and samples[-1][0] > samples[0][0] and sent != self.total:
            parts.append(f"{(samples[-1][1] - samples[0][1]) / ((samples[-1][0] - samples[0][0]) / 1e9):.0f} fps")
        dropping = {name: s.dropped for name, s in stats.items() if s.dropped and not _is_sink(s.kind)}
        parts.append(f"dropped {sum(dropping.values())}")
        parts.append(f"poses {poses}")
        if dropping:
            parts.append(f"({', '.join(sorted(dropping))} cannot keep up: frames dropped)")
        return "  ".join(parts)

    def close(self) -> None:
        """Stop watching; print the summary (unless quiet)."""
        self._stop.set()
        self._thread.join(timeout=JOIN_S)  # a thread still inside Zenoh as Python shuts down would abort it
        for subscriber in self._subscribers:
            subscriber.undeclare()
        if self.display.progress:  # the last figures once more, then the line makes way for the summary
            self.display.out.write("\x1b[K" + self.progress_line() + "\r\x1b[K")
        if self.display.summary:
            self._say(self.summary())

    def summary(self) -> str:
        """The end-of-job text (see the module docstring)."""
        with self._lock:
            stats = {name: s for name, s in self.figures.stats.items() if name in self.spec.nodes}
            poses = {target: Counter(c) for target, c in self.figures.poses.items()}
            pose_errors = self.figures.pose_errors
            rate = delivered_rate(self.figures, not self.lossless, self.asked)
        lines = [f"job summary ({time.monotonic() - self._started:.1f} s):", "  " + self._source_line(stats, rate)]
        lines += ["  nodes:", *("    " + row for row in _node_table(self.spec, stats).splitlines())]
        lines += ["  poses by target:", *("    " + row for row in _pose_table(poses, pose_errors).splitlines())]
        for name, s in sorted(stats.items()):
            if s.dropped and not _is_sink(s.kind):
                lines.append(f"  {name} dropped {_drop_detail(s)}: it could not keep up, and frames are "
                             f"latest-wins (only the newest wait); {_drop_advice(s.kind)}")
        for name, node in self.spec.nodes.items():
            declared = kind(node.kind)
            if declared.sink is None:
                continue
            for what, where in declared.sink.files(declared.validate(node.params)):
                lines.append(f"  {what}: {where}" + ("" if name in stats else " (no statistics from its node)"))
        lines.append("  " + (self.losses(stats) or "every frame accounted for: no node dropped a frame or missed one"))
        return "\n".join(lines)

    def losses(self, stats: dict[str, NodeStats] | None = None) -> str | None:
        """One line saying which nodes dropped frames, missed frames on the bus, could not join them or were
        restarted (losing the frames they held); None when none did."""
        if stats is None:
            with self._lock:
                stats = {name: s for name, s in self.figures.stats.items() if name in self.spec.nodes}
        parts = []
        if self.restarts:
            parts.append("restarted (the frames they held are lost) " +
                         ", ".join(f"{name} {count}x" for name, count in sorted(self.restarts.items())))
        for what, count in (("dropped", lambda s: s.dropped), ("missing (never arrived)", lambda s: s.missing),
                            ("unjoined", lambda s: s.unjoined)):
            counts = {name: count(s) for name, s in sorted(stats.items()) if count(s)}
            if counts:
                parts.append(f"{what} {sum(counts.values())} ({', '.join(f'{n} {c}' for n, c in counts.items())})")
        return None if not parts else "frames lost: " + "; ".join(parts)

    def _source_line(self, stats: dict[str, NodeStats], rate: float | None) -> str:
        source = stats.get(self.source)
        if source is None:
            return f"source {self.source}: no statistics (it never came up?)"
        sent = frames_sent(source)
        text = f"source {self.source}: {sent}" + (f" of {self.total}" if self.total else "") + " frames sent"
        if rate is not None:
            text += f", at {rate:.1f} fps" + (f" of the {self.asked:g} asked" if self.asked else "")
        late = source.skipped.get("late", 0)
        if late:
            text += f"; {late} late"
        slow = rate is not None and self.asked and rate < SLOW_SOURCE * self.asked
        if self.lossless and slow:
            text += ": lossless, at the pace of the slowest node"
        elif late or slow:
            text += ": the source could not keep the pace asked"
        return text


def _node_table(spec: PipelineSpec, stats: dict[str, NodeStats]) -> str:
    rows: list[tuple[str, ...]] = [("NODE", "KIND", "IN", "DONE", "OUT", "DROPPED", "MISSING", "UNJOINED",
                                    "DECODE_ERR", "SKIPPED")]
    for name, node in spec.nodes.items():
        s = stats.get(name)
        if s is None:
            rows.append((name, node.kind, *("?",) * 7, ""))
            continue
        skipped = ", ".join(f"{reason} {n}" for reason, n in sorted(s.skipped.items()))
        rows.append((name, s.kind, str(s.received), str(s.processed), str(s.published), str(s.dropped),
                     str(s.missing), str(s.unjoined), str(s.decode_errors), skipped or "-"))
    return format_table(rows)


def _pose_table(poses: dict[str, Counter[str]], errors: int) -> str:
    if not poses:
        return "no poses" + (f" ({errors} pose messages could not be read)" if errors else "")
    states = [s.value for s in TrackingState if any(c[s.value] for c in poses.values())]
    rows: list[tuple[str, ...]] = [("TARGET", "POSES", *(s.upper() for s in states))]
    for target, counts in sorted(poses.items()):
        rows.append((target, str(sum(counts.values())), *(str(counts[s]) for s in states)))
    table = format_table(rows)
    return table + (f"\n{errors} pose messages could not be read" if errors else "")


def _drop_advice(kind_name: str) -> str:
    """How to have a node of ``kind_name`` take every frame."""
    try:
        fields = kind(kind_name).params.model_fields
    except ValueError:
        fields = {}
    queue = next((name for name in ("depth", "backlog") if name in fields), None)
    slower = "ask a lower --fps"
    return f"for every frame, {slower} or queue more of them (--{queue} N)" if queue else f"for every frame, {slower}"


def _drop_detail(stats: NodeStats) -> str:
    """``N of M frames on KEY, ...`` for each input of ``stats`` that dropped some, then ``N of M sets of KEY + KEY``
    for each latest-wins join that did."""
    inputs = [f"{s.dropped} of {s.messages} on {s.key}" for s in stats.streams if s.direction == "in" and s.dropped]
    joins = [f"{group.dropped} of {group.sets} sets of {' + '.join(i.key for i in group.inputs)}"
             for group in stats.synced if group.dropped]
    return ", ".join(inputs + joins)
