"""Wire codec: round trips of every message type, zero-copy frames, hostile payloads, JSON schemas."""

from __future__ import annotations

import contextlib
import json
import struct
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from strategies import MESSAGES

from protocol import (
    Blobs,
    DecodeError,
    ErrorReport,
    Header,
    Image,
    ImageTarget,
    ImageTargets,
    Message,
    Pose,
    decode,
    encode,
)
from protocol.codec import ALIGN, MAGIC, is_frame
from protocol.message import message_types
from protocol.schemas import json_schema, write_schemas

FAST = settings(max_examples=100, deadline=None)
any_message = st.sampled_from(sorted(MESSAGES)).flatmap(MESSAGES.__getitem__)


def frame_header(payload: bytes) -> tuple[dict[str, Any], int]:
    """The JSON header of a frame payload and the offset where it ends."""
    (length,) = struct.unpack_from("<I", payload, 8)
    return json.loads(payload[12 : 12 + length]), 12 + length


def reframe(payload: bytes, edit: Callable[[dict[str, Any]], None], room: int = 4 * ALIGN) -> bytes:
    """``payload`` with its frame header edited; the arrays move ``room`` bytes on to make space for it."""
    header, _ = frame_header(payload)
    descriptors = [d for d in header.values() if isinstance(d, dict) and "offset" in d]
    data_start = min(d["offset"] for d in descriptors)
    for descriptor in descriptors:
        descriptor["offset"] += room
    edit(header)
    text = json.dumps(header, separators=(",", ":")).encode()
    padding = data_start + room - 12 - len(text)
    assert padding >= 0, "edited header does not fit before the arrays"
    return payload[:8] + struct.pack("<I", len(text)) + text + bytes(padding) + payload[data_start:]


def image(rows: int = 3, cols: int = 5) -> Image:
    data = np.arange(rows * cols, dtype=np.uint8).reshape(rows, cols)
    return Image(header=Header(stamp_ns=7, frame_id="cam0", seq=1), encoding="mono8", data=data)


def card() -> ImageTargets:
    corners = ((-0.04, 0.03, 0.0), (0.04, 0.03, 0.0), (0.04, -0.03, 0.0), (-0.04, -0.03, 0.0))
    return ImageTargets(header=Header(stamp_ns=1), targets=(
        ImageTarget(name="card", frame_id="target/card", width_m=0.08, height_m=0.06, corners=corners),))


def report() -> ErrorReport:
    return ErrorReport(header=Header(stamp_ns=7), node="echo", kind="decode", detail="bad frame")


# --- round trips ---


def test_every_registered_schema_has_a_strategy():
    assert set(MESSAGES) == set(message_types())


@pytest.mark.parametrize("schema", sorted(MESSAGES))
@FAST
@given(data=st.data())
def test_round_trip(schema: str, data: st.DataObject):
    message = data.draw(MESSAGES[schema])
    payload = encode(message)
    decoded = decode(payload)
    assert type(decoded) is type(message)
    assert decoded == message
    assert encode(decoded) == payload  # deterministic: re-encoding gives the same bytes
    if not is_frame(type(message)):
        assert list(json.loads(payload))[:2] == ["schema", "version"]


@pytest.mark.parametrize("schema", sorted(s for s, cls in message_types().items() if is_frame(cls)))
@FAST
@given(data=st.data(), wrap=st.sampled_from([bytes, bytearray, memoryview]))
def test_frame_arrays_are_aligned_read_only_views(schema: str, data: st.DataObject, wrap: type):
    message = data.draw(MESSAGES[schema])
    payload = wrap(encode(message))
    decoded = decode(payload)
    assert decoded == message
    header, header_end = frame_header(bytes(payload))
    buffer = np.frombuffer(payload, dtype=np.uint8)
    for name in type(message).ARRAY_FIELDS:
        array, offset = getattr(decoded, name), header[name]["offset"]
        assert offset % ALIGN == 0 and offset >= header_end
        assert not array.flags.writeable
        assert array.tobytes() == getattr(message, name).tobytes()  # bit for bit, -0.0 included
        if array.size:
            assert np.shares_memory(array, buffer)
            assert array.ctypes.data - buffer.ctypes.data == offset


def plain_frame_decode(payload: bytes) -> Message:
    """A frame decoded the plain way, as a reference: the header by ``json``, each array copied out
    by ``np.frombuffer``, the message validated by pydantic."""
    header, _ = frame_header(payload)
    cls = message_types()[header.pop("schema")]
    header.pop("version")
    for name in cls.ARRAY_FIELDS:
        descriptor = header[name]
        dtype = np.dtype(descriptor["dtype"]).newbyteorder("<")
        count = int(np.prod(descriptor["shape"]))
        header[name] = np.frombuffer(payload, dtype, count, descriptor["offset"]).reshape(descriptor["shape"]).copy()
    return cls.model_validate(header)


@pytest.mark.parametrize("schema", sorted(s for s, cls in message_types().items() if is_frame(cls)))
@FAST
@given(data=st.data())
def test_frames_decode_as_the_plain_reference_does(schema: str, data: st.DataObject):
    payload = encode(data.draw(MESSAGES[schema]))
    assert decode(payload) == plain_frame_decode(payload)


def test_array_nan_and_infinity_travel_bit_for_bit():
    odd = np.array([np.nan, -np.inf, np.inf, -0.0], dtype=np.float32)
    odd.view(np.uint32)[0] = 0x7FC0BEEF  # a NaN with a payload
    message = Blobs(header=Header(stamp_ns=1), centroids=np.zeros((4, 2)), areas=odd[::-1], radii=odd,
                    quality=np.zeros(4, np.float32), flags=np.zeros(4, np.uint8))
    decoded = decode(encode(message))
    assert decoded.radii.tobytes() == odd.tobytes()
    assert decoded.areas.tobytes() == odd[::-1].tobytes()


def test_arrays_decoded_from_a_bytearray_are_read_only():
    payload = bytearray(encode(image()))
    decoded = decode(payload)
    with pytest.raises(ValueError, match="read-only"):
        decoded.data[0, 0] = 1


# --- hostile payloads ---


def decode_error(payload: bytes) -> DecodeError:
    with pytest.raises(DecodeError) as caught:
        decode(payload)
    return caught.value


@FAST
@given(st.binary() | st.binary().map(MAGIC.__add__) | st.binary().map(lambda b: MAGIC + b"\x01\0\0\0" + b))
def test_random_bytes_are_refused(payload: bytes):
    assert decode_error(payload).size == len(payload)


json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats(allow_nan=False) | st.text(),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner, max_size=4),
    max_leaves=20,
)


@FAST
@given(document=json_values, schema=st.sampled_from(sorted(MESSAGES)), framed=st.booleans())
def test_arbitrary_json_never_raises_anything_but_decode_error(document: Any, schema: str, framed: bool):
    if isinstance(document, dict):
        document = {"schema": schema, "version": 1, **document}
    text = json.dumps(document).encode()
    payload = MAGIC + struct.pack("<B3xI", 1, len(text)) + text if framed else text
    with contextlib.suppress(DecodeError):
        assert isinstance(decode(payload), Message)


@FAST
@given(message=any_message, data=st.data())
def test_mutated_payloads_never_raise_anything_but_decode_error(message: Message, data: st.DataObject):
    payload = bytearray(encode(message))
    for _ in range(data.draw(st.integers(1, 4))):
        payload[data.draw(st.integers(0, len(payload) - 1))] = data.draw(st.integers(0, 255))
    with contextlib.suppress(DecodeError):
        assert isinstance(decode(bytes(payload)), Message)


@FAST
@given(message=any_message, data=st.data())
def test_truncated_payloads_are_refused(message: Message, data: st.DataObject):
    payload = encode(message)
    cut = data.draw(st.integers(0, len(payload) - 1))
    assert decode_error(payload[:cut]).size == cut


@pytest.mark.parametrize("payload", [encode(image()), encode(report())], ids=["frame", "json"])
def test_every_truncation_is_refused(payload: bytes):
    for cut in range(len(payload)):
        assert decode_error(payload[:cut]).size == cut


def test_every_flipped_byte_of_a_frame_header_is_refused():
    payload = encode(image())
    _, header_end = frame_header(payload)
    for at in range(header_end):
        flipped = bytearray(payload)
        flipped[at] ^= 0xFF
        decode_error(bytes(flipped))


def test_reserved_preamble_bytes_must_be_zero():
    payload = bytearray(encode(image()))
    payload[6] = 1
    assert "reserved" in str(decode_error(bytes(payload)))


def test_unknown_frame_layout_is_refused():
    payload = bytearray(encode(image()))
    payload[4] = 2
    assert "frame layout 2" in str(decode_error(bytes(payload)))


def test_frame_header_longer_than_payload_is_refused():
    payload = bytearray(encode(image()))
    payload[8:12] = struct.pack("<I", len(payload))
    assert "frame header needs" in str(decode_error(bytes(payload)))


@pytest.mark.parametrize(
    ("document", "expected"),
    [
        ([1, 2], "not a JSON object"),
        ({"version": 1}, 'no "schema" name'),
        ({"schema": 7, "version": 1}, 'no "schema" name'),
        ({"schema": "artrack.Nope", "version": 1}, "unknown schema 'artrack.Nope'"),
        ({"schema": "artrack.ErrorReport"}, "version None is not understood"),
        ({"schema": "artrack.ErrorReport", "version": 2}, "version 2 is not understood"),
        ({"schema": "artrack.ErrorReport", "version": "1"}, "version '1' is not understood"),
        ({"schema": "artrack.ErrorReport", "version": True}, "version True is not understood"),
        ({"schema": "artrack.Image", "version": 1}, "sent as JSON, but this schema travels the other way"),
    ],
)
def test_json_payload_faults_are_named(document: Any, expected: str):
    assert expected in str(decode_error(json.dumps(document).encode()))


def test_json_field_that_does_not_validate_names_schema_and_field():
    document = json.loads(encode(Pose(header=Header(stamp_ns=1), child_frame_id="marker/7")))
    document["covariance"] = [0.0] * 5
    error = decode_error(json.dumps(document).encode())
    assert error.schema == "artrack.Pose"
    assert "covariance" in str(error)


def test_not_utf8_is_refused():
    assert "neither an artrack frame nor JSON" in str(decode_error(b"\xff\xfe{"))


def _set(name: str, value: Any) -> Callable[[dict[str, Any]], None]:
    return lambda header: header.__setitem__(name, value)


def _descriptor(**changes: Any) -> Callable[[dict[str, Any]], None]:
    return lambda header: header["data"].update(changes)


FRAME_FAULTS = [
    (_set("schema", "artrack.Nope"), "unknown schema 'artrack.Nope'"),
    (_set("version", 99), "version 99 is not understood"),
    (_set("schema", "artrack.ErrorReport"), "sent as frame, but this schema travels the other way"),
    (_set("data", None), "array 'data': missing descriptor"),
    (_set("encoding", "mono16"), "encoding mono16 needs uint16"),
    (_set("colour", 1), "Extra inputs are not permitted"),
    (_descriptor(offset=10**6), "needs bytes 1000000..1000015"),
    (_descriptor(offset=4), "bad offset 4"),
    (_descriptor(offset="64"), "bad offset '64'"),
    (_descriptor(shape=[-3, -5]), "bad shape [-3, -5]"),
    (_descriptor(shape=[2**40, 2**40]), "payload ends at"),
    (_descriptor(shape=[1.5, 10]), "bad shape"),
    (_descriptor(shape=[1] * 9), "bad shape"),
    (_descriptor(shape=[4, 5]), "payload ends at"),  # more elements than were sent
    (_descriptor(dtype="complex128"), "dtype 'complex128' not allowed"),
    (_descriptor(dtype="object"), "dtype 'object' not allowed"),
    (_descriptor(dtype="float64", shape=[1, 1]), "dtype float64 not in"),  # on the wire, not in this field
    (_descriptor(shape=[15]), "does not fit"),
]


@pytest.mark.parametrize(("edit", "expected"), FRAME_FAULTS, ids=[e for _, e in FRAME_FAULTS])
def test_frame_header_faults_are_named(edit: Callable[[dict[str, Any]], None], expected: str):
    error = decode_error(reframe(encode(image()), edit))
    assert expected in str(error)


def test_a_frame_header_that_is_not_json_is_named():
    payload = encode(image())
    _, header_end = frame_header(payload)
    broken = payload[:12] + b'{"schema":'.ljust(header_end - 12) + payload[header_end:]
    assert "frame header is not JSON" in str(decode_error(broken))


def test_decode_error_names_schema_and_size():
    payload = reframe(encode(image()), _descriptor(offset=10**6))
    error = decode_error(payload)
    assert (error.schema, error.size) == ("artrack.Image", len(payload))
    assert str(error).startswith(f"cannot decode artrack.Image payload ({len(payload)} bytes): ")


# --- JSON schemas ---
# jsonschema is not installed in the venv (nor a project dependency), so the exported schemas are checked
# with the small validator below. It covers exactly the keywords pydantic emits and fails on any other
# assertion keyword, so a schema it does not understand cannot pass unchecked.

_ANNOTATIONS = {"title", "description", "default", "$schema", "$id", "$defs", "x-artrack-layout"}
_TYPES: dict[str, Callable[[Any], bool]] = {
    "object": lambda v: isinstance(v, dict),
    "array": lambda v: isinstance(v, list),
    "string": lambda v: isinstance(v, str),
    "integer": lambda v: isinstance(v, int) and not isinstance(v, bool),
    "number": lambda v: isinstance(v, int | float) and not isinstance(v, bool),
    "boolean": lambda v: isinstance(v, bool),
    "null": lambda v: v is None,
}


def schema_errors(value: Any, schema: dict[str, Any], root: dict[str, Any], path: str = "$") -> list[str]:
    """Where ``value`` breaks ``schema`` (JSON Schema 2020-12, the subset pydantic writes)."""
    errors: list[str] = []
    for keyword, rule in schema.items():
        if keyword in _ANNOTATIONS:
            continue
        if keyword == "$ref":
            *_, name = rule.split("/")
            errors += schema_errors(value, root["$defs"][name], root, path)
        elif keyword == "anyOf":
            if all(schema_errors(value, option, root, path) for option in rule):
                errors.append(f"{path}: matches no anyOf option")
        elif keyword == "const":
            if value != rule or isinstance(value, bool) != isinstance(rule, bool):
                errors.append(f"{path}: {value!r} is not {rule!r}")
        elif keyword == "enum":
            if value not in rule:
                errors.append(f"{path}: {value!r} not in {rule}")
        elif keyword == "type":
            if not _TYPES[rule](value):
                errors.append(f"{path}: {value!r} is not of type {rule}")
        elif keyword in ("properties", "required", "additionalProperties"):
            if not isinstance(value, dict):
                continue
            if keyword == "properties":
                for name, sub in rule.items():
                    if name in value:
                        errors += schema_errors(value[name], sub, root, f"{path}.{name}")
            elif keyword == "required":
                errors += [f"{path}: {name} missing" for name in rule if name not in value]
            elif rule is False:
                errors += [f"{path}: unexpected {name}" for name in value if name not in schema["properties"]]
        elif keyword in ("items", "prefixItems", "minItems", "maxItems"):
            if not isinstance(value, list):
                continue
            if keyword == "items":
                skip = len(schema.get("prefixItems", ()))
                for i, item in enumerate(value[skip:], start=skip):
                    errors += schema_errors(item, rule, root, f"{path}[{i}]")
            elif keyword == "prefixItems":
                for i, (item, sub) in enumerate(zip(value, rule, strict=False)):
                    errors += schema_errors(item, sub, root, f"{path}[{i}]")
            elif (len(value) < rule) if keyword == "minItems" else (len(value) > rule):
                errors.append(f"{path}: {len(value)} items breaks {keyword} {rule}")
        elif keyword == "minLength":
            if isinstance(value, str) and len(value) < rule:
                errors.append(f"{path}: {value!r} is shorter than {rule}")
        elif keyword in ("minimum", "exclusiveMinimum"):
            if _TYPES["number"](value) and (value < rule if keyword == "minimum" else value <= rule):
                errors.append(f"{path}: {value!r} breaks {keyword} {rule}")
        else:
            raise AssertionError(f"the test validator does not know the keyword {keyword!r} at {path}")
    return errors


def payload_document(payload: bytes) -> dict[str, Any]:
    """The JSON a schema describes: the whole payload, or the header inside a frame."""
    return frame_header(payload)[0] if payload[:4] == MAGIC else json.loads(payload)


@FAST
@given(message=any_message)
def test_exported_schema_validates_the_payload(message: Message):
    schema = json_schema(type(message))
    assert schema_errors(payload_document(encode(message)), schema, schema) == []


@pytest.mark.parametrize(
    ("message", "change"),
    [
        (report(), {"version": 2}),
        (report(), {"schema": "artrack.Pose"}),
        (report(), {"unexpected": 1}),
        (report(), {"count": 0}),
        (report(), {"header": {"stamp_ns": -1}}),
        (report(), {"header": {"frame_id": "no stamp"}}),
        (Pose(header=Header(stamp_ns=1), child_frame_id="x"), {"state": "confused"}),
        (Pose(header=Header(stamp_ns=1), child_frame_id="x"), {"covariance": ["a"]}),
        (Pose(header=Header(stamp_ns=1), child_frame_id="x"), {"transform": {"rotation": [0, 0, 1]}}),
        (image(), {"data": {"dtype": "complex64", "shape": [3, 5], "offset": 128}}),
        (image(), {"data": {"dtype": "uint8", "shape": [3, -5], "offset": 128}}),
        (image(), {"data": {"dtype": "uint8", "shape": [3, 5]}}),
        (image(), {"encoding": "rgb8"}),
        (card(), {"targets": [{**json.loads(encode(card()))["targets"][0], "name": ""}]}),
        (card(), {"targets": [{**json.loads(encode(card()))["targets"][0], "width_m": 0}]}),
    ],
    ids=lambda v: "" if isinstance(v, Message) else json.dumps(v),
)
def test_exported_schema_refuses_broken_documents(message: Message, change: dict[str, Any]):
    schema = json_schema(type(message))
    document = {**payload_document(encode(message)), **change}
    assert schema_errors(document, schema, schema) != []


def test_write_schemas_writes_one_file_per_message(tmp_path):
    paths = write_schemas(tmp_path / "schemas")
    assert sorted(p.name for p in paths) == sorted(f"{name}.json" for name in message_types())
    for path in paths:
        schema = json.loads(path.read_text())
        cls = message_types()[path.stem]
        assert schema == json_schema(cls)
        assert schema["title"] == cls.SCHEMA
        assert schema["properties"]["schema"] == {"const": cls.SCHEMA}
        assert schema["properties"]["version"] == {"const": cls.VERSION}
        assert schema["required"][:2] == ["schema", "version"]
        assert schema["x-artrack-layout"] == ("frame" if is_frame(cls) else "json")


def test_a_frame_header_with_an_inline_array_is_refused():
    header = json.dumps({"schema": "artrack.Image", "version": 1, "header": {"stamp_ns": 1, "frame_id": "", "seq": 0},
                          "encoding": "mono8", "data": [[1, 2], [3, 4]]}, separators=(",", ":")).encode()
    payload = struct.pack("<4sB3sI", MAGIC, 1, bytes(3), len(header)) + header
    with pytest.raises(DecodeError, match="missing descriptor"):
        decode(payload)


def test_an_older_version_a_class_still_reads_decodes_and_others_are_refused():
    from protocol.system import NodeStats

    stats = NodeStats(header=Header(stamp_ns=1), node="n", kind="k", host="h", pid=1, uptime_s=0.0)
    old = encode(stats).replace(b'"version":3', b'"version":1', 1)
    assert decode(old) == stats
    with pytest.raises(DecodeError, match="version 4 is not understood"):
        decode(encode(stats).replace(b'"version":3', b'"version":4', 1))


def test_encode_names_an_array_dtype_that_may_not_travel():
    unchecked = Blobs.model_construct(header=Header(stamp_ns=1), centroids=np.zeros((1, 2), np.float16),
                                      areas=np.zeros(1, np.float32), radii=np.zeros(1, np.float32),
                                      quality=np.zeros(1, np.float32), flags=np.zeros(1, np.uint8))
    with pytest.raises(TypeError, match="dtype float16 may not travel"):
        encode(unchecked)
