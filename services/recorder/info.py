"""What a recording holds: channels, schemas, message counts, duration, rates and sizes.

Built from one front-to-back pass (``reading.Scan``), so it works on truncated and damaged
files too and then describes their intact part; it also says whether the file has its
summary (the index seeking readers use) and what the recorder wrote about itself
(``artrack.recording`` / ``artrack.recorder`` metadata, see the package docstring), and which
other files on disk belong to the same recording (split parts, continuations of a restarted
recorder: ``writing.recording_parts``).
Rates are per channel: (messages - 1) / (last - first log time).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from services.recorder.reading import Damage, Scan, indexed
from services.recorder.writing import RECORDER_METADATA, RECORDING_METADATA, recording_parts

MIB = 1 << 20


@dataclass
class ChannelInfo:
    """One channel: its key, schema name ('' for raw payloads), message encoding and counts."""

    key: str
    schema: str
    encoding: str
    messages: int = 0
    payload_bytes: int = 0
    first_ns: int = 0
    last_ns: int = 0

    @property
    def rate_hz(self) -> float | None:
        span = self.last_ns - self.first_ns
        return (self.messages - 1) / (span / 1e9) if self.messages > 1 and span > 0 else None


@dataclass
class RecordingInfo:
    """A recording's contents (its intact part when ``damage`` is set)."""

    path: str
    size_bytes: int
    indexed: bool
    library: str
    damage: Damage | None
    channels: list[ChannelInfo] = field(default_factory=list)
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    parts: list[str] = field(default_factory=list)
    """Every file of the recording on disk, this one first, when it has split parts or continuations."""

    @property
    def messages(self) -> int:
        return sum(c.messages for c in self.channels)

    @property
    def payload_bytes(self) -> int:
        return sum(c.payload_bytes for c in self.channels)

    @property
    def first_ns(self) -> int | None:
        return min((c.first_ns for c in self.channels if c.messages), default=None)

    @property
    def last_ns(self) -> int | None:
        return max((c.last_ns for c in self.channels if c.messages), default=None)

    @property
    def duration_s(self) -> float:
        first, last = self.first_ns, self.last_ns
        return 0.0 if first is None or last is None else (last - first) / 1e9

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready, with the derived figures included."""
        return {**asdict(self), "damage": None if self.damage is None else asdict(self.damage),
                "messages": self.messages, "payload_bytes": self.payload_bytes, "first_ns": self.first_ns,
                "last_ns": self.last_ns, "duration_s": self.duration_s,
                "channels": [{**asdict(c), "rate_hz": c.rate_hz} for c in self.channels]}


def summarise(path: Path | str) -> RecordingInfo:
    """Read ``path`` once and describe it (raises ``reading.NotMcap`` for a non-MCAP file)."""
    scan = Scan(path)
    channels: dict[int, ChannelInfo] = {}
    for recorded in scan.messages():
        info = channels.get(recorded.channel.id)
        if info is None:
            info = channels[recorded.channel.id] = ChannelInfo(
                recorded.channel.topic, recorded.schema.name if recorded.schema else "",
                recorded.channel.message_encoding, first_ns=recorded.message.log_time)
        info.messages += 1
        info.payload_bytes += len(recorded.message.data)
        info.first_ns = min(info.first_ns, recorded.message.log_time)
        info.last_ns = max(info.last_ns, recorded.message.log_time)
    parts = [str(p) for p in recording_parts(Path(path))]
    return RecordingInfo(str(path), scan.size, indexed(scan.path), scan.header.library if scan.header else "",
                         scan.damage, sorted(channels.values(), key=lambda c: (c.key, c.schema)), scan.metadata,
                         parts if parts != [str(path)] else [])


def format_info(info: RecordingInfo) -> str:
    """A human-readable report: file facts, then one row per channel."""
    lines = [f"file       {info.path}",
             f"size       {info.size_bytes / MIB:.2f} MiB, "
             + ("indexed (summary present)" if info.indexed else "not indexed (no summary: the writer did not finish)"),
             "status     " + ("intact" if info.damage is None
                              else f"DAMAGED: {info.damage} (the figures below are its intact part)"),
             f"library    {info.library or '-'}"]
    recording = info.metadata.get(RECORDING_METADATA)
    if recording:
        where, keys, part = (recording.get(name, "?") for name in ("namespace", "keys", "part"))
        continues = f", continues {recording['continues']}" if "continues" in recording else ""
        lines.append(f"recording  {where}/{recording.get('rig', '?')}, keys {keys}, part {part}{continues}")
        recorder = info.metadata.get(RECORDER_METADATA)
        counts = ", ".join(f"{name} {recorder.get(name, '?')}" for name in ("received", "dropped", "unrecognised")) \
            if recorder else "not finished (no artrack.recorder record)"
        lines.append(f"recorder   {counts}")
    if info.parts:
        lines.append(f"parts      {', '.join(Path(p).name for p in info.parts)} (the figures here are of this file)")
    rate = f", {(info.messages - 1) / info.duration_s:.1f} msg/s" if info.duration_s > 0 else ""
    lines.append(f"messages   {info.messages} in {info.duration_s:.3f} s{rate}, "
                 f"{info.payload_bytes / MIB:.2f} MiB of payload")
    if info.first_ns is not None:
        start = datetime.fromtimestamp(info.first_ns / 1e9, UTC).isoformat(timespec="milliseconds")
        lines.append(f"start      {start} (log time of the first message)")
    rows: list[tuple[str, ...]] = [("KEY", "SCHEMA", "ENCODING", "MESSAGES", "RATE(Hz)", "PAYLOAD(MiB)")]
    rows += [(c.key, c.schema or "(raw)", c.encoding, str(c.messages),
              "-" if c.rate_hz is None else f"{c.rate_hz:.2f}", f"{c.payload_bytes / MIB:.3f}") for c in info.channels]
    return "\n".join([*lines, "", *_table(rows, numeric_from=3)])


def _table(rows: list[tuple[str, ...]], numeric_from: int) -> list[str]:
    """Rows as aligned text columns; columns from ``numeric_from`` on are right-aligned."""
    widths = [max(len(row[i]) for row in rows) for i in range(len(rows[0]))]
    return ["  ".join(cell.rjust(width) if i >= numeric_from else cell.ljust(width)
                      for i, (cell, width) in enumerate(zip(row, widths, strict=True))).rstrip() for row in rows]
