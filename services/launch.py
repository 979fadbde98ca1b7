"""Turning node kinds and pipeline files into processes the supervisor runs."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

from pydantic import BaseModel

from services.bus.session import BusConfig
from services.launcher.kinds import kind
from services.launcher.pipeline import NodeSpec, PipelineSpec, load_pipeline
from services.launcher.supervisor import ProcessSpec


def node_command(kind_name: str, name: str, params: dict[str, Any]) -> tuple[str, ...]:
    """The command that runs one node in its own process."""
    return (sys.executable, "-m", "services.cli", "node", kind_name, "--name", name,
            "--params", json.dumps(params))


def check_node(name: str, spec: NodeSpec) -> None:
    """Validate a pipeline node's kind and parameters (raises ValueError naming the problem)."""
    kind(spec.kind).params(spec.params)


def params_model(kind_name: str) -> type[BaseModel]:
    """The Params model of a node kind (its ``RELOADABLE`` fields may change live)."""
    return kind(kind_name).load().Params


def read_pipeline(path: Path) -> PipelineSpec:
    """Load and fully validate a pipeline file (raises PipelineError)."""
    return load_pipeline(path, check_node)


def processes(spec: PipelineSpec, bus: BusConfig) -> list[ProcessSpec]:
    """One ProcessSpec per pipeline node, sharing ``bus``."""
    env = bus.to_env()
    return [ProcessSpec(name, node_command(node.kind, name, node.params), env, node.restart)
            for name, node in spec.nodes.items()]
