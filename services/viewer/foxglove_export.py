"""A whole recording rewritten with Foxglove's well-known schemas (``artrack export IN --format foxglove``).

The recording is read front to back with the damage-tolerant ``Scan``; each payload is decoded with
``protocol.decode`` and turned into Foxglove messages by ``services.viewer.foxglove_messages``
(topics and frames: that module's docstring). The output is an MCAP file whose channels carry
protobuf messages (``message_encoding`` ``protobuf``, schemas ``foxglove.RawImage``, ... holding their
FileDescriptorSet), zstd chunks of 1 MiB, and a summary with indexes and statistics, so Foxglove,
Rerun's MCAP loader and ``mcap`` readers open it as their own.

Each output message keeps the log time of the message it comes from (its arrival at the recorder) and
takes the artrack header's stamp as publish time. Messages are written in log-time order: the
recorder writes in arrival order, which the wall clock can contradict by a little; a window of
``REORDER_NS`` holds messages back to put them in order before they are written.
"""

from __future__ import annotations

import heapq
import itertools
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

from mcap.writer import CompressionType, Writer

from services.recorder.reading import Damage, Scan
from services.viewer.foxglove_messages import (
    DEFAULT_OPTIONS,
    FoxgloveConversion,
    FoxgloveMessage,
    FoxgloveOptions,
    Topical,
)

REORDER_NS = 2_000_000_000
"""How far back in log time (ns) a message may arrive and still be written in order."""
CHUNK_BYTES = 1 << 20


@dataclass
class FoxgloveExport:
    """What an export read and wrote: messages read, undecodable ones skipped, messages written per topic,
    and where a damaged input stopped (None when intact)."""

    read: int = 0
    undecodable: int = 0
    written: Counter[str] = field(default_factory=Counter)
    damage: Damage | None = None


class _Channels:
    """The output file's schemas and channels, registered when first used."""

    def __init__(self, writer: Writer):
        self.writer = writer
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}

    def channel(self, topic: str, message: FoxgloveMessage) -> int:
        known = self._channels.get(topic)
        if known is not None:
            return known
        schema = type(message).get_schema()
        schema_id = self._schemas.get(schema.name)
        if schema_id is None:
            schema_id = self._schemas[schema.name] = self.writer.register_schema(schema.name, schema.encoding,
                                                                                 bytes(schema.data))
        self._channels[topic] = self.writer.register_channel(topic, "protobuf", schema_id)
        return self._channels[topic]


def export_foxglove(source: Path, target: Path, options: FoxgloveOptions = DEFAULT_OPTIONS) -> FoxgloveExport:
    """Write ``target`` from the recording ``source`` (see the module docstring); ``NotMcap`` before anything
    is written when ``source`` is no MCAP file. A damaged source is converted up to its damage."""
    scan = Scan(source)
    done = FoxgloveExport()
    pending: list[tuple[int, int, int, Topical]] = []  # (log time, arrival order, publish time, message)
    order = itertools.count()
    convert = FoxgloveConversion(options)
    with open(target, "wb") as out:
        writer = Writer(out, chunk_size=CHUNK_BYTES, compression=CompressionType.ZSTD)
        writer.start(profile="", library="artrack export (foxglove)")
        channels = _Channels(writer)

        def write(until_ns: int | None) -> None:
            while pending and (until_ns is None or pending[0][0] <= until_ns):
                log_ns, sequence, stamp_ns, (topic, message) = heapq.heappop(pending)
                writer.add_message(channels.channel(topic, message), log_time=log_ns, publish_time=stamp_ns,
                                   sequence=sequence, data=message.encode())
                done.written[topic] += 1

        newest = 0
        for recorded, message in scan.decoded():
            log_ns = recorded.message.log_time
            for topical in convert(message):
                heapq.heappush(pending, (log_ns, next(order), message.header.stamp_ns, topical))
            newest = max(newest, log_ns)
            write(newest - REORDER_NS)
        write(None)
        writer.finish()
    done.read, done.undecodable, done.damage = scan.read, scan.undecodable, scan.damage
    return done
