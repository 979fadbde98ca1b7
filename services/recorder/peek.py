"""What a payload is, read from its first bytes without decoding it.

Both wire layouts (see ``protocol.codec``) begin their JSON with ``{"schema":...,"version":N,``
and, for every message the codec writes, the header follows with ``stamp_ns`` first:
JSON payloads at offset 0, frames after the 12-byte ``ARTK`` preamble. ``identify`` matches
that prefix (whitespace between tokens is tolerated) and nothing more, so it costs about a
microsecond whatever the payload's size. It does not validate the rest: a payload that
looks like a known message but would fail to decode is recorded as that message, and fails
again on replay exactly as it did live.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from protocol.codec import LAYOUT_VERSION, MAGIC, is_frame
from protocol.message import Message, message_type

FRAME_JSON_OFFSET = 12
"""Where a frame's JSON header starts: after magic, layout byte, 3 reserved bytes, u32 length."""

_PREFIX = re.compile(
    rb'\{\s*"schema"\s*:\s*"([^"\\]{1,200})"\s*,\s*"version"\s*:\s*(\d{1,9})\s*'
    rb'(?:,\s*"header"\s*:\s*\{\s*"stamp_ns"\s*:\s*(\d{1,30}))?'
)


@dataclass(frozen=True)
class Identity:
    """A payload's message class (None when it is not a message this build knows) and stamp.

    ``stamp_ns`` is the header's ``stamp_ns`` when it was found right after the version;
    ``reason`` says why ``cls`` is None.
    """

    cls: type[Message] | None
    stamp_ns: int | None = None
    reason: str = ""


def identify(payload: bytes) -> Identity:
    """The identity of one payload (JSON or frame layout); never raises."""
    framed = payload[:4] == MAGIC
    if framed and (len(payload) < FRAME_JSON_OFFSET or payload[4] != LAYOUT_VERSION):
        return Identity(None, reason="truncated frame preamble or unknown frame layout")
    match = _PREFIX.match(payload, FRAME_JSON_OFFSET if framed else 0)
    if match is None:
        return Identity(None, reason='neither an artrack frame nor JSON starting with "schema" and "version"')
    schema, version = match.group(1).decode("utf-8", "replace"), int(match.group(2))
    stamp = int(match.group(3)) if match.group(3) is not None else None
    cls = message_type(schema)
    if cls is None:
        return Identity(None, stamp, f"unknown schema {schema!r}")
    if version != cls.VERSION:
        return Identity(None, stamp, f"{schema} version {version} (this build knows version {cls.VERSION})")
    if framed != is_frame(cls):
        return Identity(None, stamp, f"{schema} sent as {'frame' if framed else 'JSON'}, but it travels the other way")
    return Identity(cls, stamp)
