"""Where a job's nodes run: the processes given (a tracker's template, a pipeline file), or others.

``artrack run --processes separate`` runs every node in a process of its own; ``single`` runs every
node but the sinks (recorder, viewer, foxglove: they write files at their own pace) in one process,
``pipeline``; ``given`` (the default) keeps the grouping of the template or the file. Then each
``--process NODE=NAME`` moves one node into process ``NAME`` (``NODE=`` alone: a process of its own).
``--nice [NODE=]N`` and ``--cpus [NODE=]LIST`` set the priority and CPUs a node asks for its process
(``services.launcher.scheduling``; without ``NODE=``: every node but the sinks).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal

from pydantic import ValidationError

from services.launcher.kinds import kind
from services.launcher.pipeline import PipelineError, PipelineSpec, describe
from services.launcher.scheduling import parse_cpus, parse_nice

Layout = Literal["given", "separate", "single"]
LAYOUTS: tuple[Layout, ...] = ("given", "separate", "single")
SINGLE = "pipeline"
"""The process ``single`` puts the nodes in."""


def laid_out(spec: PipelineSpec, layout: Layout = "given", moves: Sequence[str] = ()) -> PipelineSpec:
    """``spec`` with its nodes placed by ``layout``, then by ``moves`` (``NODE=NAME`` texts); PipelineError naming a
    move that is not ``NODE=NAME`` or names no node of ``spec``."""
    places: dict[str, str | None] = {name: node.process for name, node in spec.nodes.items()}
    if layout == "separate":
        places = dict.fromkeys(places)
    elif layout == "single":
        places = {name: None if kind(node.kind).sink is not None else SINGLE for name, node in spec.nodes.items()}
    for move in moves:
        name, sep, process = move.partition("=")
        if not sep or name not in places:
            raise PipelineError(f"--process {move!r}: give NODE=PROCESS (NODE= for a process of its own) with NODE "
                                f"one of {', '.join(spec.nodes)}")
        places[name] = process or None
    nodes = {name: node.model_copy(update={"process": places[name]}) for name, node in spec.nodes.items()}
    try:
        return PipelineSpec.model_validate({**spec.model_dump(), "nodes": nodes})
    except ValidationError as exc:
        raise PipelineError(f"processes: {describe(exc)}") from exc


def scheduled(spec: PipelineSpec, nice: Sequence[str] = (), cpus: Sequence[str] = ()) -> PipelineSpec:
    """``spec`` with ``--nice [NODE=]N`` and ``--cpus [NODE=]LIST`` applied in order (without ``NODE=``: every node
    but the sinks); PipelineError naming a flag that is malformed, names no node of ``spec`` or gives the nodes of
    one process different CPUs."""
    asked: dict[str, dict[str, object]] = {name: {} for name in spec.nodes}
    for flag, texts, parse in (("nice", nice, parse_nice), ("cpus", cpus, parse_cpus)):
        for text in texts:
            name, sep, value = text.rpartition("=")
            if sep and name not in spec.nodes:
                raise PipelineError(f"--{flag} {text!r}: no node {name!r} (nodes: {', '.join(spec.nodes)})")
            try:
                parsed = parse(value)
            except ValueError as exc:
                raise PipelineError(f"--{flag} {text!r}: {exc}") from exc
            targets = [name] if sep else [n for n, node in spec.nodes.items() if kind(node.kind).sink is None]
            for target in targets:
                asked[target][flag] = parsed
    nodes = {name: node.model_copy(update=asked[name]) for name, node in spec.nodes.items()}
    try:
        return PipelineSpec.model_validate({**spec.model_dump(), "nodes": nodes})
    except ValidationError as exc:
        raise PipelineError("--cpus: " + "; ".join(p["msg"].removeprefix("Value error, ") for p in exc.errors())
                            ) from exc
