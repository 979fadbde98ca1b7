"""Changing node parameters while the nodes run.

A node kind declares the fields of its ``Params`` that may change live in a class variable,
``RELOADABLE: ClassVar[frozenset[str]]`` (thresholds, rates); any other field needs a
restart. A node that honours live changes wraps its params in ``LiveParams`` (through
``Node.configurable``), which answers ``ConfigChange`` requests on ``keys.config(name)``.
A change is all or nothing: one unknown, non-reloadable or invalid field refuses the whole
request, with a reason per field, and leaves the node as it was.

``plan_reload`` compares a running pipeline with its re-read file (SIGHUP to ``artrack
up``): the reloadable field changes it yields are pushed to the nodes; anything else (a
node added, removed or of another kind, a changed non-reloadable field, ``[bus]`` or
``[supervisor]``) refuses the reload with reasons naming node and field.
"""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Generic, TypeVar

import zenoh
from pydantic import BaseModel, ValidationError

from protocol.codec import encode
from protocol.keys import Keys
from protocol.message import Header
from protocol.system import ConfigAnswer, ConfigChange
from services.client.discovery import first_answers
from services.runtime.pipeline import PipelineSpec

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
    refused = {name: ("no such parameter" if name not in cls.model_fields else "not reloadable: needs a restart")
               for name in values if name not in allowed}
    if refused:
        raise Refused(refused)
    try:
        return cls.model_validate({**params.model_dump(exclude_unset=True), **values})
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
        dumped = self.value.model_dump(mode="json")
        return {name: json.dumps(dumped[name]) for name in sorted(reloadable(type(self.value)))}

    def answer(self, node: str, change: ConfigChange) -> ConfigAnswer:
        """Apply ``change`` (values as JSON text) and say what happened."""
        values, bad = {}, {}
        for name, text in change.values.items():
            try:
                values[name] = json.loads(text)
            except json.JSONDecodeError as exc:
                bad[name] = f"not JSON: {exc}"
        try:
            if bad:
                raise Refused(bad)
            self.change(values)
        except Refused as exc:
            return self._answer(node, refused=exc.reasons)
        return self._answer(node, applied=dict(change.values))

    def _answer(self, node: str, **outcome: dict[str, str]) -> ConfigAnswer:
        return ConfigAnswer(header=Header(stamp_ns=time.time_ns()), node=node, params=self.reloadable_values(),
                            **outcome)


def request_change(session: zenoh.Session, keys: Keys, node: str, values: dict[str, Any],
                   timeout_s: float) -> ConfigAnswer | None:
    """Ask node ``node`` to apply ``values`` (field -> value); its answer, or None if none came
    within ``timeout_s``."""
    change = ConfigChange(header=Header(stamp_ns=time.time_ns()), values={k: json.dumps(v) for k, v in values.items()})
    key = keys.config(node)
    found = first_answers(session, key, ConfigAnswer, timeout_s, payload=encode(change))
    return found.get(key)


@dataclass
class ReloadPlan:
    """What a re-read pipeline file asks for: live changes per node, or the reasons it cannot be had."""

    changes: dict[str, dict[str, Any]] = field(default_factory=dict)
    refused: list[str] = field(default_factory=list)


def plan_reload(running: PipelineSpec, wanted: PipelineSpec,
                params_of: Callable[[str], type[BaseModel]]) -> ReloadPlan:
    """The live changes that turn ``running`` into ``wanted``; ``params_of(kind)`` is a kind's Params
    model. A field dropped from the file goes back to its default. Any other difference goes into
    ``refused`` (node and field named)."""
    plan = ReloadPlan()
    for table in ("bus", "supervisor"):
        if getattr(running, table) != getattr(wanted, table):
            plan.refused.append(f"[{table}] changed: needs a restart of `artrack up`")
    for name in sorted(wanted.nodes.keys() - running.nodes.keys()):
        plan.refused.append(f"node {name}: new node: needs a restart of `artrack up`")
    for name in sorted(running.nodes.keys() - wanted.nodes.keys()):
        plan.refused.append(f"node {name}: removed: needs a restart of `artrack up`")
    for name in sorted(running.nodes.keys() & wanted.nodes.keys()):
        old, new = running.nodes[name], wanted.nodes[name]
        if (old.kind, old.restart) != (new.kind, new.restart):
            what = "kind" if old.kind != new.kind else "restart"
            plan.refused.append(f"node {name}: {what} changed: needs a restart of `artrack up`")
            continue
        before, after = old.params, new.params
        cls = params_of(new.kind)
        allowed = reloadable(cls)
        changed = {k: after[k] if k in after else cls.model_fields[k].get_default(call_default_factory=True)
                   for k in before.keys() | after.keys() if before.get(k) != after.get(k)}
        for key in sorted(changed.keys() - allowed):
            plan.refused.append(f"node {name}: field {key} is not reloadable ({new.kind}): needs a restart")
        if changed and changed.keys() <= allowed:
            plan.changes[name] = changed
    return plan
