"""Changing a running pipeline's parameters: asking one node, or planning a reload of the whole file.

``plan_reload`` compares a running pipeline with its re-read file (SIGHUP to ``artrack
up``): the reloadable field changes it yields are pushed to the nodes with
``request_change``; anything else (a node added, removed or of another kind, a changed
non-reloadable field, its process, priority or CPUs, ``[bus]`` or ``[supervisor]``) refuses the
reload with reasons naming node and field. The node's side is ``services.runtime.reconfig``.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import zenoh
from pydantic import BaseModel

from protocol.codec import encode
from protocol.keys import Keys
from protocol.message import Header
from protocol.system import ConfigAnswer, ConfigChange
from services.bus.discovery import first_answers
from services.launcher.pipeline import PipelineSpec
from services.runtime.params import flat_fields
from services.runtime.reconfig import reloadable


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
        what = next((field for field in ("kind", "restart", "process", "nice", "cpus")
                     if getattr(old, field) != getattr(new, field)), None)
        if what is not None:
            plan.refused.append(f"node {name}: {what} changed: needs a restart of `artrack up`")
            continue
        before, after = old.params, new.params
        cls = params_of(new.kind)
        allowed = reloadable(cls)
        defaults = flat_fields(cls)
        changed = {k: after[k] if k in after else defaults[k].default
                   for k in before.keys() | after.keys() if before.get(k) != after.get(k)}
        for key in sorted(changed.keys() - allowed):
            plan.refused.append(f"node {name}: field {key} is not reloadable ({new.kind}): needs a restart")
        if changed and changed.keys() <= allowed:
            plan.changes[name] = changed
    return plan
