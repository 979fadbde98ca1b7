"""Reading MCAP files front to back, intact or not, and recovering damaged ones.

``Scan`` walks the data section record by record (opening chunks, checking their CRCs) and
stops at the data-end record, or at the first damage: a file that ends inside a record or
before its data end (the writer was killed), a chunk that does not decompress or whose CRC
is wrong, a record that does not parse, a message on an undeclared channel. It then says
where (``Damage.offset``: the byte where the first damaged or missing record starts, which is
also the end of the intact part) and why. Everything before is yielded; nothing after is
trusted (a corrupt length field would make anything further a guess).

The summary section is not read: messages come in file order, which for artrack recordings
is arrival order. ``recover`` copies the intact part into a new, finished and indexed file.
"""

from __future__ import annotations

import struct
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from io import BytesIO
from pathlib import Path

from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.reader import make_reader
from mcap.records import Attachment, Channel, Chunk, Header, Message, Metadata, Schema
from mcap.stream_reader import breakup_chunk
from mcap.writer import Writer

from protocol.codec import DecodeError, decode
from protocol.message import Message as WireMessage

EXIT_DAMAGED = 3
"""Exit code of the commands that read a recording when it is damaged (its intact part was used)."""
MAGIC = b"\x89MCAP0\r\n"
_RECORD_HEAD = struct.Struct("<BQ")
_PARSERS: dict[int, Callable[[ReadDataStream], Record | Chunk]] = {
    Opcode.HEADER: Header.read, Opcode.SCHEMA: Schema.read, Opcode.CHANNEL: Channel.read,
    Opcode.CHUNK: Chunk.read, Opcode.METADATA: Metadata.read, Opcode.ATTACHMENT: Attachment.read,
}
_END = (Opcode.DATA_END, Opcode.FOOTER)

Record = Header | Schema | Channel | Message | Metadata | Attachment


class NotMcap(ValueError):
    """The file is missing, unreadable or not an MCAP file at all."""


@dataclass(frozen=True)
class Damage:
    """Where the intact part of a file ends, and why."""

    offset: int
    size: int
    reason: str

    def __str__(self) -> str:
        return f"stopped at byte {self.offset} of {self.size}: {self.reason}"


@dataclass(frozen=True)
class Recorded:
    """One message with its channel and schema (None for schema id 0)."""

    channel: Channel
    schema: Schema | None
    message: Message


class Scan:
    """One front-to-back pass over ``path``; iterate ``records()``, ``messages()`` or ``decoded()`` once.

    Opening checks the magic (``NotMcap`` otherwise). After the pass, ``damage`` is None when
    the data section ended properly; ``header`` and ``metadata`` (name -> the last record of
    that name) fill in as they are passed; ``read`` and ``undecodable`` count what ``decoded()`` met.
    """

    def __init__(self, path: Path | str):
        self.path = Path(path)
        self.header: Header | None = None
        self.metadata: dict[str, dict[str, str]] = {}
        self.damage: Damage | None = None
        self.read = 0
        self.undecodable = 0
        try:
            self.size = self.path.stat().st_size
            with open(self.path, "rb") as file:
                magic = file.read(len(MAGIC))
        except OSError as exc:
            raise NotMcap(f"cannot read {self.path}: {exc.strerror or exc}") from exc
        if magic != MAGIC:
            raise NotMcap(f"{self.path} is not an MCAP file")

    def records(self) -> Iterator[Record]:
        """Header, schemas, channels, messages, metadata and attachments in file order."""
        with open(self.path, "rb") as file:
            file.seek(len(MAGIC))
            offset = len(MAGIC)
            channels: set[int] = set()
            while True:
                head = file.read(_RECORD_HEAD.size)
                if len(head) < _RECORD_HEAD.size:
                    self._damaged(offset, "the file ends before its data-end record (it was not finished)" if not head
                                  else "the file ends inside a record header")
                    return
                opcode, length = _RECORD_HEAD.unpack(head)
                end = offset + _RECORD_HEAD.size + length
                if opcode in _END:
                    return
                if end > self.size:
                    present = self.size - offset - _RECORD_HEAD.size
                    self._damaged(offset, f"the file ends inside a {_name(opcode)} record "
                                          f"({present} of {length} bytes present)")
                    return
                if opcode in _PARSERS or opcode == Opcode.MESSAGE:
                    try:
                        records = _parse(opcode, file.read(length))
                    except _Bad as bad:
                        self._damaged(offset, str(bad))
                        return
                    for record in records:
                        problem = _out_of_place(record, self.header is None, channels)
                        if problem:
                            self._damaged(offset, problem)
                            return
                        if isinstance(record, Header):
                            self.header = record
                        elif isinstance(record, Channel):
                            channels.add(record.id)
                        elif isinstance(record, Metadata):
                            self.metadata[record.name] = record.metadata
                        yield record
                else:
                    file.seek(end)
                offset = end

    def _damaged(self, offset: int, reason: str) -> None:
        self.damage = Damage(offset, self.size, reason)

    def decoded(self) -> Iterator[tuple[Recorded, WireMessage]]:
        """Every intact message that the wire codec decodes, with its record, in file order; the others are
        counted in ``undecodable`` and skipped."""
        for recorded in self.messages():
            self.read += 1
            try:
                message = decode(recorded.message.data)
            except DecodeError:
                self.undecodable += 1
                continue
            yield recorded, message

    def messages(self) -> Iterator[Recorded]:
        """Every intact message in file order, with its channel and schema."""
        schemas: dict[int, Schema] = {}
        channels: dict[int, Channel] = {}
        for record in self.records():
            if isinstance(record, Schema):
                schemas[record.id] = record
            elif isinstance(record, Channel):
                channels[record.id] = record
            elif isinstance(record, Message):
                channel = channels[record.channel_id]
                yield Recorded(channel, schemas.get(channel.schema_id), record)


def _parse(opcode: int, body: bytes) -> list[Record]:
    try:
        stream = ReadDataStream(BytesIO(body))
        record = Message.read(stream, len(body)) if opcode == Opcode.MESSAGE else _PARSERS[opcode](stream)
    except (McapError, struct.error, UnicodeDecodeError, ValueError) as exc:
        raise _Bad(f"malformed {_name(opcode)} record ({type(exc).__name__}: {exc})") from exc
    if isinstance(record, Chunk):
        try:
            parts = breakup_chunk(record, validate_crc=True)
        except Exception as exc:  # zstd / lz4 / CRC / parse errors: the chunk is unusable either way
            raise _Bad(f"corrupt {record.compression or 'uncompressed'} chunk ({type(exc).__name__}: {exc})") \
                from exc
        return [part for part in parts if isinstance(part, Schema | Channel | Message)]
    return [record]


class _Bad(Exception):
    """A record that is present but unusable."""


def _out_of_place(record: Record, first: bool, channels: set[int]) -> str:
    """Why ``record`` cannot be where it is ('' when it can)."""
    if first and not isinstance(record, Header):
        return f"the first record is a {type(record).__name__}, not a Header"
    if isinstance(record, Message) and record.channel_id not in channels:
        return f"a message on channel {record.channel_id}, which was never declared"
    return ""


def _name(opcode: int) -> str:
    try:
        return Opcode(opcode).name.title().replace("_", "")
    except ValueError:
        return f"unknown (opcode {opcode:#x})"


def indexed(path: Path) -> bool:
    """True when the file has a readable summary (a seeking MCAP reader can use its index)."""
    try:
        with open(path, "rb") as file:
            return make_reader(file).get_summary() is not None
    except (McapError, OSError, struct.error, ValueError):
        return False


@dataclass(frozen=True)
class Recovered:
    """What ``recover`` copied, and the damage that ended the copy (None: the source was intact)."""

    messages: int
    damage: Damage | None


def recover(source: Path, target: Path) -> Recovered:
    """Copy every intact record of ``source`` (schemas, channels, messages with their times
    and sequence numbers, metadata, attachments) into ``target``, a new finished, indexed file
    (FileExistsError when ``target`` exists: a recording is never overwritten).
    """
    scan = Scan(source)
    schema_ids: dict[int, int] = {0: 0}
    channel_ids: dict[int, int] = {}
    messages = 0
    with open(target, "xb") as file:
        writer = Writer(file)
        for record in scan.records():  # the first one, if any, is the header
            if isinstance(record, Header):
                writer.start(profile=record.profile, library=record.library)
            elif isinstance(record, Schema) and record.id not in schema_ids:  # writers may repeat them
                schema_ids[record.id] = writer.register_schema(record.name, record.encoding, record.data)
            elif isinstance(record, Channel) and record.id not in channel_ids:
                channel_ids[record.id] = writer.register_channel(
                    record.topic, record.message_encoding, schema_ids.get(record.schema_id, 0), record.metadata)
            elif isinstance(record, Message):
                writer.add_message(channel_ids[record.channel_id], log_time=record.log_time, data=record.data,
                                   publish_time=record.publish_time, sequence=record.sequence)
                messages += 1
            elif isinstance(record, Metadata):
                writer.add_metadata(record.name, record.metadata)
            elif isinstance(record, Attachment):
                writer.add_attachment(record.create_time, record.log_time, record.name, record.media_type,
                                      record.data)
        if scan.header is None:
            writer.start()
        writer.finish()
    return Recovered(messages, scan.damage)
