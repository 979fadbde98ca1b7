"""Changing node parameters while the nodes run.

A node kind declares the parameters of its ``Params`` that may change live in a class variable,
``RELOADABLE: ClassVar[frozenset[str]]`` (thresholds, rates), by their flat names
(``services.runtime.params``); any other parameter needs a restart. A node that honours live
changes wraps its params in ``LiveParams`` (through ``Node.configurable``), which answers
``ConfigChange`` requests on ``keys.config(name)``. A change is all or nothing: one unknown,
non-reloadable or invalid field refuses the whole request, with a reason per field, and leaves the
node as it was.
The launcher's side (asking a node for a change, planning a pipeline reload) is
``services.launcher.reload``.
"""

from __future__ import annotations

import json
import threading
import time
import types
from collections.abc import Callable
from typing import Any, Generic, TypeVar, Union, get_args, get_origin

from pydantic import BaseModel, ValidationError

from protocol.message import Header
from protocol.system import ConfigAnswer, ConfigChange
from services.runtime.params import flat_dump, flat_fields

P = TypeVar("P", bound=BaseModel)


def reloadable(params_cls: type[BaseModel]) -> frozenset[str]:
    """Fields of ``params_cls`` that may change while its node runs."""
    return getattr(params_cls, "RELOADABLE", frozenset())


class Refused(ValueError):
    """A parameter change that was not applied: ``reasons`` maps each offending field to why."""

    def __init__(self, reasons: dict[str, str]):
        super().__init__("; ".join(f"{name}: {why}" for name, why in reasons.items()))
        self.reasons = reasons


def changed_params(params: P, values: dict[str, Any]) -> P:
    """``params`` with ``values`` applied, validated by its model; raises Refused naming each bad field."""
    cls = type(params)
    allowed = reloadable(cls)
    refused = {name: ("no such parameter" if name not in flat_fields(cls) else "not reloadable: needs a restart")
               for name in values if name not in allowed}
    if refused:
        raise Refused(refused)
    try:
        return cls.model_validate({**flat_dump(params, exclude_unset=True), **values})
    except ValidationError as exc:
        raise Refused({".".join(str(p) for p in problem["loc"]) or "(params)": problem["msg"]
                       for problem in exc.errors()}) from exc


class LiveParams(Generic[P]):
    """A node's parameters, changed in place by ``change`` (thread-safe); ``value`` is the current model.

    ``apply(new)`` runs before a change is kept: it puts the new values to work (rebuilds a
    detector, say) and may raise ValueError to refuse them.
    """

    def __init__(self, params: P, apply: Callable[[P], None] | None = None):
        self.value = params
        self._apply = apply
        self._lock = threading.Lock()

    def change(self, values: dict[str, Any]) -> None:
        """Apply ``values`` (field -> new value) or raise Refused, leaving everything as it was."""
        with self._lock:
            new = changed_params(self.value, values)
            if self._apply is not None:
                try:
                    self._apply(new)
                except ValueError as exc:
                    raise Refused({name: str(exc) for name in values}) from exc
            self.value = new

    def reloadable_values(self) -> dict[str, str]:
        """Every reloadable field's current value, as JSON text."""
        dumped = flat_dump(self.value, mode="json")
        return {name: json.dumps(dumped[name]) for name in sorted(reloadable(type(self.value)))}

    def answer(self, node: str, change: ConfigChange) -> ConfigAnswer:
        """Apply ``change`` (values as JSON text) and say what happened: ``applied`` holds each changed field's
        value as the node holds it now (``"1.0"`` typed for a float field is applied as ``1.0``).

        A value that arrives as a JSON string for a list or mapping field is that field's JSON
        (``artrack config --set`` sends what was typed as text; the node knows the field's type).
        """
        values, bad = {}, {}
        fields = flat_fields(type(self.value))
        for name, text in change.values.items():
            try:
                value = json.loads(text)
                if isinstance(value, str) and name in fields and _container(fields[name].info.annotation):
                    value = json.loads(value)
                values[name] = value
            except json.JSONDecodeError as exc:
                bad[name] = f"not JSON: {exc}"
        try:
            if bad:
                raise Refused(bad)
            self.change(values)
        except Refused as exc:
            return self._answer(node, refused=exc.reasons)
        held = self.reloadable_values()
        return self._answer(node, applied={name: held[name] for name in values})

    def _answer(self, node: str, **outcome: dict[str, str]) -> ConfigAnswer:
        return ConfigAnswer(header=Header(stamp_ns=time.time_ns()), node=node, params=self.reloadable_values(),
                            **outcome)


def _container(annotation: Any) -> bool:
    """True for a list, tuple, set or dict type, optional or not."""
    if get_origin(annotation) in (Union, types.UnionType):
        return any(_container(arg) for arg in get_args(annotation) if arg is not type(None))
    return get_origin(annotation) in (list, tuple, set, dict)
