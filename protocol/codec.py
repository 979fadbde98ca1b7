"""Wire codec: messages to payload bytes and back.

Two payload layouts, chosen by the message class:

* Messages without array fields travel as one UTF-8 JSON object whose first two keys are
  ``"schema"`` and ``"version"``, followed by the message's fields. Any JSON library can
  read them; stock MCAP readers decode them with the exported JSON Schema.
* Messages with array fields travel as a *frame*::

      offset 0   b"ARTK"                      magic
      offset 4   u8  layout version (1), 3 zero bytes
      offset 8   u32 little-endian length L of the JSON header
      offset 12  JSON header (L bytes): {"schema", "version", the other fields,
                 each array field as {"dtype", "shape", "offset"}}
      then       zero padding, and each array's raw little-endian bytes, C order,
                 starting at its ``offset`` (a multiple of 64 from the payload start)

  Decoding wraps the payload's own buffer: arrays are read-only numpy views into it,
  no copy, no base64, no pickle.

``peek`` says what a payload is (schema, version, header, media type) from its JSON part
alone, without validating the message's other fields or reading its arrays.

Every failure to decode or peek (garbage, truncation, unknown schema, wrong version, a field
that does not validate) raises :class:`DecodeError` and nothing else.
"""

from __future__ import annotations

import functools
import json
import math
import re
import struct
from typing import Any, NamedTuple

import numpy as np
from pydantic import ValidationError
from pydantic_core import from_json

from protocol.arrays import WIRE_DTYPES, dtype_name
from protocol.message import Header, Message, message_type

MAGIC = b"ARTK"
LAYOUT_VERSION = 1
ALIGN = 64
_PREAMBLE = struct.Struct("<4sB3sI")

MEDIA_JSON = "application/json"
MEDIA_FRAME = "application/vnd.artrack.frame"


class DecodeError(ValueError):
    """A payload that cannot be turned into a message; ``schema`` is set when it was readable."""

    def __init__(self, reason: str, schema: str | None = None, size: int | None = None):
        self.reason = reason
        self.schema = schema
        self.size = size
        what = f"{schema} payload" if schema else "payload"
        where = f" ({size} bytes)" if size is not None else ""
        super().__init__(f"cannot decode {what}{where}: {reason}")


def is_frame(cls: type[Message]) -> bool:
    """True when ``cls`` travels as a binary frame (it has array fields)."""
    return bool(cls.ARRAY_FIELDS)


def media_type(cls: type[Message]) -> str:
    """The payload's media type: ``MEDIA_JSON`` or ``MEDIA_FRAME``."""
    return MEDIA_FRAME if is_frame(cls) else MEDIA_JSON


@functools.cache
def _prefix(cls: type[Message]) -> str:
    return f'{{"schema":{json.dumps(cls.SCHEMA)},"version":{cls.VERSION}'


@functools.cache
def _array_names(cls: type[Message]) -> frozenset[str]:
    return frozenset(cls.ARRAY_FIELDS)


def _descriptors(arrays: list[tuple[str, np.ndarray]], offsets: list[int]) -> str:
    """``"name":{"dtype":..,"shape":[..],"offset":..}`` for each array, comma-joined (the JSON tail)."""
    return ",".join(
        f'"{name}":{{"dtype":"{dtype_name(wire.dtype)}","shape":[{",".join(map(str, wire.shape))}],"offset":{at}}}'
        for (name, wire), at in zip(arrays, offsets, strict=True))


def encode(message: Message) -> bytes:
    """Serialise ``message`` to payload bytes (JSON or frame, by its class)."""
    cls = type(message)
    if not is_frame(cls):
        body = message.model_dump_json()
        return (_prefix(cls) + "," + body[1:]).encode()
    arrays = [(name, _wire(getattr(message, name))) for name in cls.ARRAY_FIELDS]
    fields = message.model_dump_json(exclude=_array_names(cls))  # type: ignore[arg-type]  # any set works
    head = _prefix(cls) + "," + fields[1:-1] + ("," if len(fields) > 2 else "")
    # Array offsets depend on the header's length and the header holds the offsets:
    # lay out after a first guess and move the arrays back until the header fits.
    start = _align(_PREAMBLE.size + len(head) + 64)
    while True:
        offsets, offset = [], start
        for _, wire in arrays:
            offsets.append(offset)
            offset = _align(offset + wire.nbytes)
        header = (head + _descriptors(arrays, offsets) + "}").encode()
        if _PREAMBLE.size + len(header) <= start:
            break
        start = _align(_PREAMBLE.size + len(header))
    parts: list[bytes | memoryview] = [_PREAMBLE.pack(MAGIC, LAYOUT_VERSION, bytes(3), len(header)), header]
    position = _PREAMBLE.size + len(header)
    for (_, wire), at in zip(arrays, offsets, strict=True):
        parts.append(bytes(at - position))
        parts.append(wire.data.cast("B") if wire.nbytes else b"")
        position = at + wire.nbytes
    return b"".join(parts)


def _wire(array: np.ndarray) -> np.ndarray:
    name = dtype_name(array.dtype)
    if name is None:
        raise TypeError(f"dtype {array.dtype} may not travel (message built without validation?)")
    return np.ascontiguousarray(array.astype(WIRE_DTYPES[name], copy=False))


def _align(n: int) -> int:
    return (n + ALIGN - 1) // ALIGN * ALIGN


def decode(payload: bytes | bytearray | memoryview) -> Message:
    """Turn payload bytes into the message they encode; raise DecodeError on any fault.

    Array fields of the result are read-only views into ``payload``.
    """
    size = len(payload)
    try:
        if bytes(payload[:4]) == MAGIC:
            return _decode_frame(payload)
        return _decode_json(payload)
    except DecodeError:
        raise
    except Exception as exc:  # any other fault of a hostile payload becomes a DecodeError
        raise DecodeError(f"{type(exc).__name__}: {exc}", size=size) from exc


def _lookup(document: Any, size: int, *, framed: bool) -> tuple[type[Message], dict[str, Any]]:
    if not isinstance(document, dict):
        raise DecodeError("not a JSON object", size=size)
    schema, version = document.pop("schema", None), document.pop("version", None)
    if not isinstance(schema, str):
        raise DecodeError('no "schema" name', size=size)
    cls = message_type(schema)
    if cls is None:
        raise DecodeError(f"unknown schema {schema!r}", schema=schema, size=size)
    if isinstance(version, bool) or (version != cls.VERSION and version not in cls.READS_OLDER):
        raise DecodeError(f"version {version!r} is not understood (this build reads version {cls.VERSION})",
                          schema=schema, size=size)
    if framed != is_frame(cls):
        layout = "frame" if framed else "JSON"
        raise DecodeError(f"sent as {layout}, but this schema travels the other way", schema=schema, size=size)
    return cls, document


def _problems(exc: ValidationError, within: tuple[str, ...] = ()) -> str:
    """Each validation error as ``field.path: message`` (paths under ``within``), ``; ``-joined."""
    return "; ".join(f"{'.'.join(map(str, (*within, *e['loc']))) or '(message)'}: {e['msg']}" for e in exc.errors())


def _validate(cls: type[Message], document: dict[str, Any], size: int) -> Message:
    try:
        return cls.model_validate(document)
    except ValidationError as exc:
        raise DecodeError(_problems(exc), schema=cls.SCHEMA, size=size) from exc


_HEAD = re.compile(rb'\{"schema":"([A-Za-z0-9_.\-]+)","version":([0-9]+),')


def _fast(document: bytes) -> Message | None:
    """The JSON message, validated in one pass by pydantic's JSON parser, when ``document`` starts the
    way ``encode`` writes it and validates; None sends the caller down the careful path, which says
    exactly what is wrong."""
    head = _HEAD.match(document)
    if head is None:
        return None
    cls = message_type(head.group(1).decode())
    if cls is None or int(head.group(2)) != cls.VERSION or is_frame(cls):
        return None
    try:
        return cls.__pydantic_validator__.validate_json(b"{" + document[head.end():])
    except ValidationError:
        return None


def _decode_json(payload: bytes | bytearray | memoryview) -> Message:
    fast = _fast(bytes(payload))
    if fast is not None:
        return fast
    size = len(payload)
    try:
        document = json.loads(bytes(payload) if isinstance(payload, memoryview) else payload)
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise DecodeError(f"neither an artrack frame nor JSON ({exc})", size=size) from exc
    cls, document = _lookup(document, size, framed=False)
    return _validate(cls, document, size)


def _header_end(payload: bytes | bytearray | memoryview) -> int:
    """Where a frame's JSON header ends, after checking the preamble; DecodeError for a bad one."""
    size = len(payload)
    if size < _PREAMBLE.size:
        raise DecodeError("truncated frame preamble", size=size)
    _, layout, reserved, header_len = _PREAMBLE.unpack_from(payload, 0)
    if layout != LAYOUT_VERSION:
        raise DecodeError(f"frame layout {layout} is not understood (this build reads {LAYOUT_VERSION})", size=size)
    if reserved != bytes(3):
        raise DecodeError(f"reserved preamble bytes must be zero, got {reserved.hex()}", size=size)
    end = _PREAMBLE.size + header_len
    if end > size:
        raise DecodeError(f"frame header needs {end} bytes, payload has {size}", size=size)
    return end


def _decode_frame(payload: bytes | bytearray | memoryview) -> Message:
    size = len(payload)
    end = _header_end(payload)
    try:
        document = from_json(bytes(payload[_PREAMBLE.size : end]))
    except ValueError as exc:
        raise DecodeError(f"frame header is not JSON ({exc})", size=size) from exc
    cls, document = _lookup(document, size, framed=True)
    for name in cls.ARRAY_FIELDS:
        document[name] = _view(payload, document.get(name), name, end, cls.SCHEMA)
    return _validate(cls, document, size)


def _extent(descriptor: Any, name: str, header_end: int, size: int, schema: str) -> tuple[str, list[int], int, int]:
    """``(dtype, shape, offset, count)`` of an array descriptor that lies within the payload's
    ``size`` bytes after the header; DecodeError naming the array otherwise."""

    def fail(reason: str) -> DecodeError:
        return DecodeError(f"array {name!r}: {reason}", schema=schema, size=size)

    if not isinstance(descriptor, dict):
        raise fail("missing descriptor")
    dtype, shape, offset = descriptor.get("dtype"), descriptor.get("shape"), descriptor.get("offset")
    if dtype not in WIRE_DTYPES:
        raise fail(f"dtype {dtype!r} not allowed")
    if not isinstance(shape, list) or not all(isinstance(n, int) and n >= 0 for n in shape) or len(shape) > 8:
        raise fail(f"bad shape {shape!r}")
    if not isinstance(offset, int) or offset < header_end:
        raise fail(f"bad offset {offset!r}")
    count = math.prod(shape)
    nbytes = count * WIRE_DTYPES[dtype].itemsize
    if offset + nbytes > size:
        raise fail(f"needs bytes {offset}..{offset + nbytes}, payload ends at {size}")
    return dtype, shape, offset, count


def _view(payload: Any, descriptor: Any, name: str, header_end: int, schema: str) -> np.ndarray:
    dtype, shape, offset, count = _extent(descriptor, name, header_end, len(payload), schema)
    array = np.frombuffer(payload, dtype=WIRE_DTYPES[dtype], count=count, offset=offset)
    array.flags.writeable = False  # frombuffer over a bytearray is writable; messages are not
    return array.reshape(shape).astype(np.dtype(dtype), copy=False)


class Peeked(NamedTuple):
    """What a payload is, as ``peek`` reads it: its message class, media type and header."""

    cls: type[Message]
    media_type: str
    stamp_ns: int
    frame_id: str
    seq: int

    @property
    def schema(self) -> str:
        return self.cls.SCHEMA

    @property
    def version(self) -> int:
        return self.cls.VERSION


def peek(payload: bytes | bytearray | memoryview) -> Peeked:
    """The message class, media type and header of ``payload``; DecodeError for garbage, a
    truncated payload, an unknown schema or version, or a header that does not validate.

    Only the JSON part is parsed (a frame's header, not its arrays, whose extents are checked
    against the payload's length); the message's other fields are not validated, so a payload
    that peeks may still fail to ``decode``.
    """
    size = len(payload)
    try:
        framed = bytes(payload[:4]) == MAGIC
        end = _header_end(payload) if framed else size
        try:
            document = from_json(bytes(payload[_PREAMBLE.size : end] if framed else payload))
        except ValueError as exc:
            what = "frame header is not JSON" if framed else "neither an artrack frame nor JSON"
            raise DecodeError(f"{what} ({exc})", size=size) from exc
        cls, document = _lookup(document, size, framed=framed)
        try:
            header = Header.model_validate(document.get("header"))
        except ValidationError as exc:
            raise DecodeError(_problems(exc, ("header",)), schema=cls.SCHEMA, size=size) from exc
        for name in cls.ARRAY_FIELDS:
            _extent(document.get(name), name, end, size, cls.SCHEMA)
        return Peeked(cls, media_type(cls), header.stamp_ns, header.frame_id, header.seq)
    except DecodeError:
        raise
    except Exception as exc:  # any other fault of a hostile payload becomes a DecodeError
        raise DecodeError(f"{type(exc).__name__}: {exc}", size=size) from exc


def to_json(message: Message, max_array_elements: int | None = None) -> dict[str, Any]:
    """A JSON-ready dict of ``message`` with its schema and version (for echo, export, logs).

    Arrays with more than ``max_array_elements`` elements are summarised as dtype and shape.
    """
    context = {"max_array_elements": max_array_elements} if max_array_elements is not None else None
    return {"schema": message.SCHEMA, "version": message.VERSION,
            **message.model_dump(mode="json", context=context)}


ARRIVAL_FIELDS = ("key", "received_ns")
"""What a sample record says of the sample itself: the key it arrived on (or was recorded on) and when."""


def sample_record(key: str, received_ns: int, message: Message,
                  max_array_elements: int | None = None) -> dict[str, Any]:
    """One line of ``artrack echo`` and of a JSON-lines export: ``key`` (the key the sample arrived on),
    ``received_ns``, then ``to_json(message)``. A message field named like one of those two (an
    ``ErrorReport``'s ``key``: the key its problem concerns) keeps its value under ``message_<name>``,
    so the arrival key is never replaced by the message's own."""
    fields = to_json(message, max_array_elements)
    record: dict[str, Any] = {"key": key, "received_ns": received_ns}
    for name, value in fields.items():
        record[f"message_{name}" if name in ARRIVAL_FIELDS else name] = value
    return record
