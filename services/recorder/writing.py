"""Payloads in, MCAP files out: one channel per (key, message type), optionally split into parts.

The layout of what is written (encodings, metadata, part names) is described in the
package docstring. ``RecordingWriter`` is not thread-safe: one thread writes.
"""

from __future__ import annotations

import glob
import json
import re
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

from mcap.well_known import MessageEncoding, SchemaEncoding
from mcap.writer import LIBRARY_IDENTIFIER, CompressionType, Writer

from protocol.codec import MEDIA_FRAME, DecodeError, Peeked, is_frame, peek
from protocol.message import Message
from protocol.schemas import json_schema

LIBRARY = f"artrack recorder; {LIBRARY_IDENTIFIER}"
RAW_ENCODING = "application/octet-stream"
RECORDING_METADATA = "artrack.recording"
RECORDER_METADATA = "artrack.recorder"
COMPRESSIONS = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}
CHUNK_BYTES = 1 << 20

Identity = Peeked | str
"""What the writer files a payload under: its ``peek``, or why it is not a message this build
knows (then it is recorded raw)."""


def identify(payload: bytes) -> Identity:
    """``protocol.codec.peek(payload)``, or the reason it failed; never raises.

    A payload that peeks is filed under its message class even if its other fields would
    fail to decode: it is recorded as it travelled and fails again on replay as it did live.
    """
    try:
        return peek(payload)
    except DecodeError as exc:
        return str(exc)


def message_class(identity: Identity) -> type[Message] | None:
    """The message class a payload is filed under; None: recorded raw."""
    return identity.cls if isinstance(identity, Peeked) else None


@dataclass(frozen=True)
class Split:
    """When to start a new part: once a part holds ``size_bytes`` (estimated on-disk size) or
    spans ``duration_ns`` of log time. Both None: never."""

    size_bytes: int | None = None
    duration_ns: int | None = None

    @property
    def active(self) -> bool:
        return self.size_bytes is not None or self.duration_ns is not None


def part_path(out: Path, index: int) -> Path:
    """``OUT_000.mcap`` for part 0 of ``OUT.mcap`` (at least three digits)."""
    return out.with_name(f"{out.stem}_{index:03d}{out.suffix}")


def continuation_path(out: Path, number: int) -> Path:
    """``OUT.partN.mcap``: where a restarted recorder of ``OUT.mcap`` goes on (``number`` 2, 3, ...)."""
    return out.with_name(f"{out.stem}.part{number}{out.suffix}")


def _split_parts(out: Path) -> list[Path]:
    """The split parts of ``out`` on disk (``OUT_000.mcap``, ...), in order."""
    found = out.parent.glob(f"{glob.escape(out.stem)}_[0-9][0-9][0-9]*{glob.escape(out.suffix)}")
    return sorted((p for p in found if p.stem[len(out.stem) + 1:].isdigit()),
                  key=lambda p: int(p.stem[len(out.stem) + 1:]))


def _begun(out: Path) -> list[Path]:
    """``out`` and its split parts, those on disk."""
    return [p for p in (out, *_split_parts(out)) if p.exists()]


def continuations(out: Path) -> list[tuple[int, list[Path]]]:
    """``(N, files)`` of every continuation of ``out`` on disk (``OUT.partN.mcap`` or its split parts), by N."""
    pattern = re.compile(rf"{re.escape(out.stem)}\.part([0-9]+)(?:_[0-9]{{3,}})?{re.escape(out.suffix)}")
    numbers = {int(m.group(1)) for p in out.parent.glob(f"{glob.escape(out.stem)}.part*{glob.escape(out.suffix)}")
               if (m := pattern.fullmatch(p.name)) and m.group(1) != "1" and not m.group(1).startswith("0")}
    return [(n, _begun(continuation_path(out, n))) for n in sorted(numbers)]


def recording_parts(out: Path) -> list[Path]:
    """Every file of the recording ``out`` on disk: ``out`` (or its split parts), then its continuations."""
    return [*_begun(out), *(p for _, files in continuations(out) for p in files)]


def check_target(out: Path) -> None:
    """Refuse (ValueError) an output whose folder is missing, or that would overwrite or join a recording:
    ``out`` itself, any split part or continuation of it."""
    if not out.parent.is_dir():
        raise ValueError(f"cannot record to {out}: folder {out.parent} does not exist")
    taken = recording_parts(out)
    if taken:
        raise ValueError(f"{taken[0]} exists: choose another name or remove it (recordings are never overwritten)")


def restart_target(out: Path) -> Path:
    """Where a restarted recorder of ``out`` writes: ``out`` if nothing of it was begun, else the next
    continuation (``OUT.part2.mcap``, then ``OUT.part3.mcap``, ...). ValueError for a missing folder."""
    if not recording_parts(out):
        check_target(out)
        return out
    begun = continuations(out)
    return continuation_path(out, begun[-1][0] + 1 if begun else 2)


def channel_encoding(cls: type[Message] | None) -> tuple[str, dict[str, str]]:
    """MCAP message encoding and channel metadata for messages of ``cls`` (None: raw payloads)."""
    if cls is None:
        return RAW_ENCODING, {"artrack.layout": "raw"}
    framed = is_frame(cls)
    return (MEDIA_FRAME if framed else MessageEncoding.JSON,
            {"artrack.layout": "frame" if framed else "json", "artrack.version": str(cls.VERSION)})


class _Part:
    """One open MCAP file."""

    def __init__(self, path: Path, compression: CompressionType, metadata: dict[str, str]):
        self.path = path
        self._file: BinaryIO = open(path, "xb")  # noqa: SIM115  (closed in finish; never overwrites)
        self._writer = Writer(self._file, chunk_size=CHUNK_BYTES, compression=compression)
        self._writer.start(library=LIBRARY)
        self._writer.add_metadata(RECORDING_METADATA, metadata)
        self._schemas: dict[str, int] = {}
        self._channels: dict[tuple[str, type[Message] | None], int] = {}
        self.messages = 0
        self.first_log_ns: int | None = None
        self._on_disk = self._file.tell()
        self._unwritten = 0

    def add(self, key: str, identity: Identity, payload: bytes, log_time_ns: int, sequence: int) -> None:
        cls = message_class(identity)
        channel = self._channels.get((key, cls))
        if channel is None:
            channel = self._channels[(key, cls)] = self._register(key, identity)
        stamp = identity.stamp_ns if isinstance(identity, Peeked) else log_time_ns
        self._writer.add_message(channel, log_time=log_time_ns, data=payload, publish_time=stamp,
                                 sequence=sequence & 0xFFFFFFFF)
        self.messages += 1
        if self.first_log_ns is None:
            self.first_log_ns = log_time_ns
        self._account(len(payload))

    def _register(self, key: str, identity: Identity) -> int:
        if not isinstance(identity, Peeked):
            encoding, metadata = channel_encoding(None)
            return self._writer.register_channel(key, encoding, 0, {**metadata, "artrack.reason": identity})
        name = identity.schema
        if name not in self._schemas:
            body = json.dumps(json_schema(identity.cls)).encode()
            self._schemas[name] = self._writer.register_schema(name, SchemaEncoding.JSONSchema, body)
        encoding, metadata = channel_encoding(identity.cls)
        return self._writer.register_channel(key, encoding, self._schemas[name], metadata)

    def _account(self, added: int) -> None:
        position = self._file.tell()
        if position != self._on_disk:  # a chunk went out: everything so far is on disk
            self._on_disk, self._unwritten = position, 0
        else:
            self._unwritten += added

    def size_estimate(self) -> int:
        """Bytes on disk plus the payload bytes still in the open chunk (an upper bound)."""
        return self._on_disk + self._unwritten

    def flush(self) -> None:
        self._writer.flush()
        self._account(0)

    def finish(self, notes: dict[str, str]) -> None:
        try:
            self._writer.add_metadata(RECORDER_METADATA, {"messages": str(self.messages), **notes})
            self._writer.finish()
        finally:
            self._file.close()


class RecordingWriter:
    """Writes payloads to ``out`` (or its parts when ``split`` is active).

    ``metadata`` goes into every file's ``artrack.recording`` record (``part`` and
    ``started_ns`` are added); ``notes()`` is called as each file is finished and its
    result written into the ``artrack.recorder`` record. The first file is created at once,
    so a recording that received nothing is still a valid, empty MCAP file.
    """

    def __init__(self, out: Path, *, split: Split = Split(), compression: str = "zstd",
                 metadata: dict[str, str] | None = None, notes: Callable[[], dict[str, str]] = dict):
        self.out = out
        self.split = split
        self.files: list[Path] = []
        self.messages = 0
        self.payload_bytes = 0
        self._compression = COMPRESSIONS[compression]
        self._metadata = dict(metadata or {})
        self._notes = notes
        self._sequences: dict[tuple[str, type[Message] | None], int] = {}
        self._part: _Part | None = self._open()

    def _open(self) -> _Part:
        index = len(self.files)
        path = part_path(self.out, index) if self.split.active else self.out
        part = _Part(path, self._compression, {**self._metadata, "part": str(index), "started_ns": str(time.time_ns())})
        self.files.append(path)
        return part

    def write(self, key: str, payload: bytes, log_time_ns: int, identity: Identity | None = None) -> None:
        """Append one payload that arrived on ``key`` at ``log_time_ns``; ``identity`` is
        ``identify(payload)``, computed here unless the caller already has it."""
        if identity is None:
            identity = identify(payload)
        part = self._part
        if part is None:
            part = self._part = self._open()
        elif (self.split.duration_ns is not None and part.first_log_ns is not None
              and log_time_ns - part.first_log_ns >= self.split.duration_ns):
            self._finish()
            part = self._part = self._open()
        slot = (key, message_class(identity))
        sequence = self._sequences.get(slot, 0)
        self._sequences[slot] = sequence + 1
        part.add(key, identity, payload, log_time_ns, sequence)
        self.messages += 1
        self.payload_bytes += len(payload)
        if self.split.size_bytes is not None and part.size_estimate() >= self.split.size_bytes:
            self._finish()

    def flush(self) -> None:
        """Write out the open chunk so that a killed process leaves every message so far readable."""
        if self._part is not None:
            self._part.flush()

    def _finish(self) -> None:
        assert self._part is not None
        part, self._part = self._part, None
        part.finish(self._notes())

    def close(self) -> None:
        """Finish the open file (summary and indexes)."""
        if self._part is not None:
            self._finish()
