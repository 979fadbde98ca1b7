"""Node parameters composed of algorithm option models, and the flat names they go by outside Python.

A node's ``Params`` holds the node's own fields (its camera, files, queue depth) and one field per
option model of the algorithms it runs (``match: MatchOptions``). Each option is declared once, by
its algorithm, with its default, constraints and description, so the defaults a node runs are the
library's. Outside Python, parameters are flat: the flags of ``artrack run``, the keys of a
pipeline file's node table, ``artrack config --set``, a kind's ``RELOADABLE``. A nested model's
fields go by the prefix its field declares with ``Flat`` (``Annotated[MatchOptions, Flat("")]``:
``gate_rms``; ``Flat("predict_")``: ``predict_gate``), or by their own names given by ``names``;
without a ``Flat``, the prefix is the field's name and ``_``. Option models nested in option models
are named the same way, the outer prefix in front of the inner one.

``NodeParams`` is the base of a ``Params`` with option models: it takes flat keys (as well as nested
values, ``match=MatchOptions(...)``), and its validation errors name the flat key
(``gate_rms: Input should be greater than 0``). ``flat_fields``, ``flat_dump`` and ``flat_location``
work on any pydantic model: a model without option models is its own flat form.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from pydantic import BaseModel, ConfigDict, ValidationError, ValidatorFunctionWrapHandler, model_validator
from pydantic.fields import FieldInfo
from pydantic_core import PydanticUndefined

__all__ = ["Flat", "FlatField", "NodeParams", "flat_dump", "flat_fields", "flat_location", "nest", "option_model"]


@dataclass(frozen=True)
class Flat:
    """How the fields of an option model nested in a node's ``Params`` are named among its flat parameters:
    ``prefix`` + the field's flat name, or the name ``names`` gives it (the nested model's flat name ->
    the name here); ``label`` is shown before each one's description in ``artrack run --help``."""

    prefix: str = ""
    names: Mapping[str, str] = field(default_factory=dict)
    label: str = ""


@dataclass(frozen=True)
class FlatField:
    """One flat parameter: its ``name``, the ``path`` of attributes that hold it in the model, the
    declaring field's ``info`` (type, constraints, description), the ``default`` the model runs with, and
    the ``label`` of the option model it belongs to ("" for none)."""

    name: str
    path: tuple[str, ...]
    info: FieldInfo
    default: Any
    label: str = ""


def option_model(info: FieldInfo) -> type[BaseModel] | None:
    """The option model a field holds (a pydantic model class as its whole annotation), else None."""
    annotation = info.annotation
    return annotation if isinstance(annotation, type) and issubclass(annotation, BaseModel) else None


def _flat(name: str, info: FieldInfo) -> Flat:
    found = [m for m in info.metadata if isinstance(m, Flat)]
    return found[0] if found else Flat(prefix=f"{name}_")


def _default(info: FieldInfo) -> Any:
    default = info.get_default(call_default_factory=True)
    return None if default is PydanticUndefined else default


@functools.cache
def flat_fields(model: type[BaseModel]) -> dict[str, FlatField]:
    """Every flat parameter of ``model``, by flat name, in declaration order; TypeError for two of one name
    or a ``Flat`` that renames a field its model lacks (a declaration to fix, not an input)."""
    found: dict[str, FlatField] = {}

    def add(flat: FlatField) -> None:
        if flat.name in found:
            raise TypeError(f"{model.__name__}: parameter {flat.name!r} is both {'.'.join(found[flat.name].path)} "
                            f"and {'.'.join(flat.path)}: give one of them another prefix or name (Flat)")
        found[flat.name] = flat

    for name, info in model.model_fields.items():
        inner = option_model(info)
        if inner is None:
            add(FlatField(name, (name,), info, _default(info)))
            continue
        how, default = _flat(name, info), _default(info)
        leaves = flat_fields(inner)
        unknown = set(how.names) - set(leaves)
        if unknown:
            raise TypeError(f"{model.__name__}.{name}: Flat names {', '.join(sorted(unknown))}, which "
                            f"{inner.__name__} does not have")
        for leaf in leaves.values():
            value = default
            for part in leaf.path:
                value = getattr(value, part, None)
            add(FlatField(how.names.get(leaf.name, how.prefix + leaf.name), (name, *leaf.path), leaf.info,
                          value if default is not None else leaf.default, how.label or leaf.label))
    taken = [name for name in model.model_fields if name in found and len(found[name].path) > 1]
    if taken:
        raise TypeError(f"{model.__name__}: parameter {taken[0]!r} is also the name of a field holding options")
    return found


def nest(model: type[BaseModel], values: Mapping[str, Any]) -> dict[str, Any]:
    """``values`` (flat keys, and nested values under a field's own name) as ``model`` validates them: each
    flat key of an option model put in place under its field. A flat key wins over the same option in a
    nested value; keys ``model`` does not know are left for its validation to refuse."""
    fields = flat_fields(model)
    nested = {key: value for key, value in values.items() if key in model.model_fields}
    for key, value in values.items():
        if key in model.model_fields:
            continue
        flat = fields.get(key)
        if flat is None:
            nested[key] = value
            continue
        table = nested
        for part in flat.path[:-1]:
            inner = table.get(part)
            if isinstance(inner, BaseModel):
                inner = {name: getattr(inner, name) for name in inner.model_fields_set}
            table[part] = dict(inner) if isinstance(inner, Mapping) else {}
            table = table[part]
        table[flat.path[-1]] = value
    return nested


def flat_dump(params: BaseModel, **dump: Any) -> dict[str, Any]:
    """``params.model_dump(**dump)`` with flat keys (``exclude_unset=True``: the parameters given)."""
    dumped = params.model_dump(**dump)
    flat: dict[str, Any] = {}
    for name, field_ in flat_fields(type(params)).items():
        value: Any = dumped
        for part in field_.path:
            if not isinstance(value, dict) or part not in value:
                break
            value = value[part]
        else:
            flat[name] = value
    return flat


def flat_location(model: type[BaseModel], loc: tuple[int | str, ...]) -> tuple[int | str, ...]:
    """A validation error's location in ``model`` with the flat name of the parameter it is in
    (``("match", "gate_rms")`` -> ``("gate_rms",)``); a location in no parameter as it is."""
    paths = {flat.path: flat.name for flat in flat_fields(model).values()}
    for end in range(len(loc), 0, -1):
        name = paths.get(tuple(str(part) for part in loc[:end]))
        if name is not None:
            return (name, *loc[end:])
    return loc


class NodeParams(BaseModel):
    """The base of a node's ``Params`` that composes option models: takes flat keys, names them in errors."""

    model_config = ConfigDict(extra="forbid")

    @model_validator(mode="wrap")
    @classmethod
    def _flat_keys(cls, data: Any, handler: ValidatorFunctionWrapHandler) -> Any:
        if isinstance(data, Mapping):
            data = nest(cls, data)
        try:
            return handler(data)
        except ValidationError as exc:
            problems = [{"type": p["type"], "loc": flat_location(cls, p["loc"]), "input": p["input"],
                         **({"ctx": p["ctx"]} if "ctx" in p else {})} for p in exc.errors()]
            raise ValidationError.from_exception_data(exc.title, problems) from None  # type: ignore[arg-type]
