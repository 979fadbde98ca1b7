"""Pipeline files: which nodes ``artrack up`` starts, each as its own process.

A pipeline is a TOML file::

    [bus]               # optional, any BusConfig field: namespace, rig, connect, listen, mode
    rig = "demo"

    [supervisor]        # optional, any SupervisorSettings field: back-off, restart budget, grace
    max_restarts = 5    # restarts allowed within window_s; past that the node is failed, left down
    window_s = 60

    [nodes.cam]         # one table per node; the table name is the node's name
    kind = "capture"    # a node kind (``artrack kinds`` lists them)
    restart = true      # restart it when it dies (default)
    fps = 30            # every other key is a parameter of the kind

    [nodes.echo]
    kind = "echo"

The whole file is validated, node parameters included, before any process starts; the
first error names the file, the field and the reason.
"""

from __future__ import annotations

import tomllib
from collections.abc import Callable
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from protocol.keys import check_name
from services.bus.session import BusConfig
from services.launcher.supervisor import SupervisorSettings


class PipelineError(ValueError):
    """A pipeline file that cannot run; the message names the file, field and reason."""


class NodeSpec(BaseModel):
    """One node of a pipeline: its kind, restart policy, and the kind's parameters (extra keys)."""

    model_config = ConfigDict(extra="allow", frozen=True)

    kind: str
    restart: bool = True

    @property
    def params(self) -> dict[str, Any]:
        return dict(self.model_extra or {})


class PipelineSpec(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    bus: dict[str, Any] = Field(default_factory=dict)
    supervisor: SupervisorSettings = Field(default_factory=SupervisorSettings)
    nodes: dict[str, NodeSpec] = Field(min_length=1)

    @field_validator("nodes")
    @classmethod
    def _names(cls, nodes: dict[str, NodeSpec]) -> dict[str, NodeSpec]:
        for name in nodes:
            check_name(name, "node name")
        return nodes


def describe(error: ValidationError, prefix: str = "") -> str:
    """One line per problem: ``field.path: reason``."""
    lines = []
    for problem in error.errors():
        path = ".".join(str(p) for p in (prefix, *problem["loc"]) if p != "")
        lines.append(f"{path or '(top level)'}: {problem['msg']}")
    return "; ".join(lines)


def load_pipeline(path: Path, check_node: Callable[[str, NodeSpec], None]) -> PipelineSpec:
    """Read and validate ``path``; ``check_node(name, spec)`` validates each node's kind and params.

    ``check_node`` raises ValueError (pydantic's ValidationError included) for a bad node.
    """
    try:
        document = tomllib.loads(path.read_text())
    except OSError as exc:
        raise PipelineError(f"{path}: cannot read: {exc.strerror}") from exc
    except tomllib.TOMLDecodeError as exc:
        raise PipelineError(f"{path}: not valid TOML: {exc}") from exc
    try:
        spec = PipelineSpec.model_validate(document)
    except ValidationError as exc:
        raise PipelineError(f"{path}: {describe(exc)}") from exc
    try:
        BusConfig.model_validate(spec.bus)
    except ValidationError as exc:
        raise PipelineError(f"{path}: {describe(exc, 'bus')}") from exc
    for name, node in spec.nodes.items():
        try:
            check_node(name, node)
        except ValidationError as exc:
            raise PipelineError(f"{path}: {describe(exc, f'nodes.{name}')}") from exc
        except ValueError as exc:
            raise PipelineError(f"{path}: nodes.{name}: {exc}") from exc
    return spec
