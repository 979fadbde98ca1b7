"""Numpy array fields for pydantic messages.

An array field is declared as ``Annotated[np.ndarray, array_field(dtypes, *shapes)]``, which
states the dtypes and the shape the field accepts (``None`` in a shape means "any length on
this axis"). On the wire an array never goes through JSON: the codec lifts it out of the
message and sends its raw little-endian bytes next to the JSON header (see ``protocol.codec``).
In JSON views of a message (``model_dump(mode="json")``, ``artrack echo``) an array is written
as nested lists, or, when the serialisation context sets ``max_array_elements`` and the array
is larger, as a short summary ``{"dtype", "shape"}``.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import numpy as np
from annotated_types import GroupedMetadata
from pydantic import PlainSerializer, PlainValidator, SerializationInfo, WithJsonSchema

WIRE_DTYPES: dict[str, np.dtype] = {
    name: np.dtype(name).newbyteorder("<")
    for name in ("uint8", "uint16", "int32", "int64", "float32", "float64")
}
"""Dtypes that may travel, by name; all are little-endian on the wire."""

_NAMES: dict[np.dtype, str] = {
    np.dtype(name).newbyteorder(order): name for name in WIRE_DTYPES for order in ("<", ">", "=")
}


def dtype_name(dtype: np.dtype) -> str | None:
    """The wire name of ``dtype`` (either byte order), or None when it may not travel.

    A dict look-up: ``dtype.name`` costs microseconds, which matters per frame.
    """
    return _NAMES.get(dtype)

ARRAY_DESCRIPTOR_SCHEMA: dict[str, Any] = {
    "type": "object",
    "description": "Raw array stored after the JSON header: dtype (little-endian), shape, byte offset.",
    "properties": {
        "dtype": {"enum": sorted(WIRE_DTYPES)},
        "shape": {"type": "array", "items": {"type": "integer", "minimum": 0}},
        "offset": {"type": "integer", "minimum": 0},
    },
    "required": ["dtype", "shape", "offset"],
}


class ArraySpec(GroupedMetadata):
    """An array field's metadata: the codec finds array fields by it, pydantic expands it into
    the field's validator, serialiser and JSON schema."""

    def __init__(self, dtypes: tuple[str, ...], shapes: tuple[tuple[int | None, ...], ...]):
        unknown = set(dtypes) - set(WIRE_DTYPES)
        if unknown:
            raise ValueError(f"dtypes not allowed on the wire: {sorted(unknown)}")
        self.dtypes = dtypes
        self.shapes = shapes

    def check(self, value: Any) -> np.ndarray:
        """Return ``value`` as an ndarray of an allowed dtype and shape, or raise ValueError."""
        array = value if isinstance(value, np.ndarray) else np.asarray(value)
        if dtype_name(array.dtype) not in self.dtypes:
            if isinstance(value, np.ndarray) or len(self.dtypes) != 1:
                raise ValueError(f"dtype {array.dtype} not in {list(self.dtypes)}")
            array = array.astype(self.dtypes[0])
        if not array.dtype.isnative:
            array = array.astype(array.dtype.newbyteorder("="))
        if not any(_shape_fits(array.shape, shape) for shape in self.shapes):
            wanted = " or ".join(_shape_text(s) for s in self.shapes)
            raise ValueError(f"shape {tuple(array.shape)} does not fit {wanted}")
        return array

    def __iter__(self) -> Iterator[object]:
        yield PlainValidator(self.check)
        yield PlainSerializer(self.serialize, when_used="json", return_type=Any)
        yield WithJsonSchema(ARRAY_DESCRIPTOR_SCHEMA)

    def serialize(self, array: np.ndarray, info: SerializationInfo) -> Any:
        limit = (info.context or {}).get("max_array_elements") if info.context else None
        if limit is not None and array.size > limit:
            return {"dtype": dtype_name(array.dtype), "shape": list(array.shape)}
        return array.tolist()


def _shape_fits(actual: tuple[int, ...], wanted: tuple[int | None, ...]) -> bool:
    return len(actual) == len(wanted) and all(w is None or a == w for a, w in zip(actual, wanted, strict=True))


def _shape_text(shape: tuple[int | None, ...]) -> str:
    return "(" + ", ".join("N" if s is None else str(s) for s in shape) + ")"


def array_field(dtypes: str | tuple[str, ...], *shapes: tuple[int | None, ...]) -> ArraySpec:
    """Metadata of an ndarray field accepting ``dtypes`` and any of ``shapes``.

    ``Annotated[np.ndarray, array_field("float32", (None, 2))]`` is an (N, 2) float32 array; a
    list input is converted when exactly one dtype is allowed; an ndarray of another dtype is refused.
    """
    return ArraySpec((dtypes,) if isinstance(dtypes, str) else tuple(dtypes), tuple(shapes))


def array_spec(metadata: list[Any]) -> ArraySpec | None:
    """The ArraySpec among a field's metadata, if the field is an array field."""
    return next((m for m in metadata if isinstance(m, ArraySpec)), None)
