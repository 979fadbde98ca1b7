"""The base of every message: the header, the schema registry, array-field bookkeeping.

Every message class names its schema and version as class variables::

    class Pose(Message):
        SCHEMA = "artrack.Pose"
        VERSION = 1

Defining such a class registers it, so the codec can decode a payload by its schema name.
Array fields (declared with ``protocol.arrays.ndarray``) may only sit at the top level of a
message; the codec sends them as raw bytes. Messages are immutable once built.
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from protocol.arrays import ArraySpec, array_spec


class Header(BaseModel):
    """Where a message comes from.

    ``stamp_ns`` is the capture time of the source frame this message derives from
    (nanoseconds, the source's clock; CLOCK_REALTIME for live sources), ``frame_id`` the
    frame the message's contents are expressed in (a camera's optical frame, ``world``),
    ``seq`` the source frame's sequence number. Outputs copy the header of their input
    frame, so consumers can join results to frames and measure end-to-end latency.
    """

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    stamp_ns: int = Field(ge=0)
    frame_id: str = ""
    seq: int = Field(default=0, ge=0)


class Struct(BaseModel):
    """A frozen part of a message (no header, no schema of its own).

    Float fields refuse NaN and infinities: JSON cannot carry them (arrays can, as raw bytes).
    """

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)


class Message(Struct):
    """A top-level message: has a header, a registered schema name and a version."""

    SCHEMA: ClassVar[str]
    VERSION: ClassVar[int]
    READS_OLDER: ClassVar[tuple[int, ...]] = ()
    """Older versions this class still decodes: they differ only by fields that have a default now, or by
    values the class's validators read as their current ones (``Pose``'s older spelling of a state)."""
    ARRAY_FIELDS: ClassVar[dict[str, ArraySpec]] = {}

    header: Header

    @classmethod
    def __pydantic_init_subclass__(cls, **kwargs: Any) -> None:
        super().__pydantic_init_subclass__(**kwargs)
        cls.ARRAY_FIELDS = {
            name: spec for name, field in cls.model_fields.items() if (spec := array_spec(field.metadata))
        }
        if "SCHEMA" in cls.__dict__:
            register(cls)

    def __eq__(self, other: object) -> bool:
        if type(other) is not type(self):
            return NotImplemented
        for name in type(self).model_fields:
            mine, theirs = getattr(self, name), getattr(other, name)
            if name in self.ARRAY_FIELDS:
                if mine.dtype != theirs.dtype or not np.array_equal(mine, theirs):
                    return False
            elif mine != theirs:
                return False
        return True

    __hash__ = None  # type: ignore[assignment]


_REGISTRY: dict[str, type[Message]] = {}


def register(cls: type[Message]) -> None:
    """Make ``cls`` decodable by its schema name; a second class with the same name is refused."""
    if not isinstance(cls.__dict__.get("VERSION"), int) or cls.VERSION < 1:
        raise TypeError(f"{cls.__name__} must set VERSION to a positive int")
    known = _REGISTRY.get(cls.SCHEMA)
    if known is not None and known.__qualname__ != cls.__qualname__:
        raise TypeError(f"schema {cls.SCHEMA!r} already registered by {known.__qualname__}")
    _REGISTRY[cls.SCHEMA] = cls


def message_types() -> dict[str, type[Message]]:
    """Every registered message class, by schema name."""
    return dict(_REGISTRY)


def message_type(schema: str) -> type[Message] | None:
    """The message class registered for ``schema``, or None."""
    return _REGISTRY.get(schema)
