"""Command-line flags generated from node parameter models, values parsed by the fields' types.

Each flat parameter (``services.runtime.params``: a field of the model, or a field of an option
model it holds, under the prefix that field declares) becomes ``--name``: a bool a ``--x/--no-x``
switch, a tuple a repeatable list (``--source a --source b`` or ``--cameras a b``), a ``Literal`` a
choice, a dict repeated ``KEY=VALUE`` pairs; the rest take one value. argparse only collects text: the model's own
validation converts it by the field's declared type, so ``--fps 30`` is a float because the
field is one, never because the text looks like a number. A dict whose values have no
declared type (``dict[str, Any]``) takes JSON values. Validation errors are reported against
the flag, not the field. A flag's help is its field's description (after the label of the option
model it belongs to), its type and the default the node runs with.
"""

from __future__ import annotations

import argparse
import json
import types
from dataclasses import dataclass
from typing import Annotated, Any, Literal, Union, get_args, get_origin

from pydantic import BaseModel, ValidationError
from pydantic.fields import FieldInfo

from services.runtime.params import flat_fields


@dataclass(frozen=True)
class Flag:
    """One generated flag: ``--option`` sets the flat parameter ``field`` of the models it was made from, declared
    by ``info``, whose node runs with ``default``; ``label`` names the option model it belongs to."""

    field: str
    option: str
    info: FieldInfo
    owner: str = ""
    default: Any = None
    label: str = ""

    @property
    def key(self) -> str:
        """What ``given_values`` files the value under: the field, or ``kind.field`` for a renamed flag."""
        return f"{self.owner}.{self.field}" if self.owner else self.field

    @property
    def dest(self) -> str:
        return self.option.removeprefix("--").replace("-", "_")


def _bare(annotation: Any) -> Any:
    """``annotation`` without ``Optional``."""
    if get_origin(annotation) in (Union, types.UnionType):
        kept = [a for a in get_args(annotation) if a is not type(None)]
        if len(kept) == 1:
            return kept[0]
    return annotation


def type_name(annotation: Any) -> str:
    """A short name of a field's type for help texts: ``float``, ``path``, ``list of str``, ``int -> float``."""
    annotation = _bare(annotation)
    origin = get_origin(annotation)
    if origin in (tuple, list):
        return f"list of {type_name(get_args(annotation)[0])}"
    if origin is dict:
        key, value = get_args(annotation)
        return f"{type_name(key)} -> {'JSON' if value is Any else type_name(value)}"
    if origin is Literal:
        return "choice"
    if origin in (Union, types.UnionType):
        return " or ".join(" or ".join(map(repr, get_args(a))) if get_origin(a) is Literal else type_name(a)
                           for a in get_args(annotation) if a is not type(None))
    if get_origin(annotation) is Annotated:
        return type_name(get_args(annotation)[0])
    name = getattr(annotation, "__name__", str(annotation))
    return "path" if name.endswith("Path") else name


def flags_for(model: type[BaseModel], skip: set[str] | frozenset[str] = frozenset(), owner: str = "") -> list[Flag]:
    """A flag per flat parameter of ``model`` but those in ``skip``; with an ``owner`` (a kind),
    ``--<owner>-<name>``.

    A model may name some flags itself in a class variable ``FLAGS`` (flat name -> option name without
    dashes), for a shorter option than the parameter's name (``--flush`` for ``flush_s``)."""
    names: dict[str, str] = getattr(model, "FLAGS", {})
    return [Flag(name, "--" + (f"{owner}_{name}" if owner else names.get(name, name)).replace("_", "-"), flat.info,
                 owner, flat.default, flat.label)
            for name, flat in flat_fields(model).items() if name not in skip]


def add_flags(group: argparse._ArgumentGroup, flags: list[Flag]) -> None:
    """Add ``flags`` to ``group``; each defaults to None (not given)."""
    for flag in flags:
        annotation = _bare(flag.info.annotation)
        origin = get_origin(annotation)
        default = flag.default
        written = " ".join(map(str, default)) if isinstance(default, tuple) else default
        shown = "" if default in (None, (), {}, "") else f"; default {written}"
        label = f"{flag.label}: " if flag.label else ""
        text = (f"{label}{flag.info.description or flag.field.replace('_', ' ')} "
                f"({type_name(flag.info.annotation)}{shown})")
        if annotation is bool:
            group.add_argument(flag.option, dest=flag.dest, action=argparse.BooleanOptionalAction, default=None,
                               help=text)
        elif origin in (tuple, list):
            group.add_argument(flag.option, dest=flag.dest, action="extend", nargs="+", metavar="VALUE", help=text)
        elif origin is dict:
            group.add_argument(flag.option, dest=flag.dest, action="append", metavar="KEY=VALUE",
                               help=text + "; repeatable")
        elif origin is Literal:
            group.add_argument(flag.option, dest=flag.dest, choices=[str(c) for c in get_args(annotation)],
                               help=text)
        else:
            group.add_argument(flag.option, dest=flag.dest, metavar=flag.field.upper(), help=text)


def _pairs(flag: Flag, given: list[str]) -> dict[str, Any]:
    annotation = _bare(flag.info.annotation)
    typed_values = get_args(annotation)[1:] != (Any,)
    values: dict[str, Any] = {}
    for pair in given:
        key, sep, text = pair.partition("=")
        if not sep or not key:
            raise ValueError(f"{flag.option} {pair!r}: give KEY=VALUE")
        if typed_values:
            values[key] = text
            continue
        try:
            values[key] = json.loads(text)
        except json.JSONDecodeError as exc:
            raise ValueError(f"{flag.option} {pair!r}: VALUE must be JSON here (a string in quotes: "
                             f"{key}='\"{text}\"')") from exc
    return values


def given_values(args: argparse.Namespace, flags: list[Flag]) -> dict[str, Any]:
    """``{flag.key: value}`` of the flags given on the command line (text, for the model to convert)."""
    values = {}
    for flag in flags:
        value = getattr(args, flag.dest, None)
        if value is None:
            continue
        values[flag.key] = _pairs(flag, value) if get_origin(_bare(flag.info.annotation)) is dict else value
    return values


def explain(error: ValidationError, flags: list[Flag], what: str) -> str:
    """A validation error of ``what`` told against the flags that set the fields."""
    options = {flag.field: flag.option for flag in flags}
    lines = []
    for problem in error.errors():
        field = str(problem["loc"][0]) if problem["loc"] else ""
        where = options.get(field) or ".".join([what, *(str(p) for p in problem["loc"])])
        message = problem["msg"].removeprefix("Value error, ")
        if problem["type"] == "literal_error":
            message = f"{message} (given {problem['input']!r})"
        lines.append(f"{where}: {message}")
    return "; ".join(lines)
