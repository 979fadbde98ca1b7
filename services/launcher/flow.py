"""A pipeline's flow: lossless or real-time, and each node's part in it (``services.runtime.flow``).

``FlowSettings`` is the pipeline file's ``[flow]`` table (``artrack run --flow``, ``--window``).
``mode = "auto"`` is lossless when every source is finite (files, a recording, a scene with a
frame count) and real-time otherwise (a camera, an endless scene, a loop). From the wiring
(which node's outputs another node's inputs match) ``plans`` tells each node what to do: a
source waits for the credits of the nodes that take its images; those nodes acknowledge each
frame; every node other than a source waits for the ends of the nodes it reads from.
"""

from __future__ import annotations

from typing import Literal

import zenoh
from pydantic import BaseModel, ConfigDict, Field

from services.launcher.kinds import kind
from services.runtime.flow import DEFAULT_WINDOW, FlowPlan

FlowMode = Literal["auto", "lossless", "realtime"]


class FlowSettings(BaseModel):
    """How frames flow from a pipeline's sources (its ``[flow]`` table)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    mode: FlowMode = Field(default="auto", description="lossless: every frame reaches every node (finite "
                           "sources); realtime: latest-wins, frames dropped by slow nodes; auto: lossless when "
                           "every source is finite")
    window: int = Field(default=DEFAULT_WINDOW, ge=1, le=10_000,
                        description="frames a lossless source may send ahead of its slowest node")


def finite(node_kind: str, params: dict) -> bool:
    """Whether a node of ``node_kind`` with ``params`` is a source that ends by itself."""
    declared = kind(node_kind)
    return declared.source is not None and declared.source.finite(declared.validate(params))


def lossless(settings: FlowSettings, sources: dict[str, tuple[str, dict]]) -> bool:
    """Whether a pipeline with ``sources`` ({name: (kind, params)}) runs lossless under ``settings``."""
    if settings.mode != "auto":
        return settings.mode == "lossless"
    return bool(sources) and all(finite(node_kind, params) for node_kind, params in sources.values())


def _meets(outputs: tuple[str, ...], inputs: tuple[str, ...]) -> bool:
    return any(zenoh.KeyExpr(o).intersects(zenoh.KeyExpr(i)) for o in outputs for i in inputs)


def plans(settings: FlowSettings, nodes: dict[str, tuple[str, dict, tuple[str, ...], tuple[str, ...]]]
          ) -> dict[str, FlowPlan]:
    """Each node's ``FlowPlan``, from ``nodes``: {name: (kind, params, inputs, outputs)} with the keys
    relative to the rig (as a resolved pipeline states them). A source's credit nodes are those whose
    inputs match its image keys; a node's upstream, the nodes (not itself) whose outputs its inputs match."""
    sources = {name: (k, p) for name, (k, p, inputs, _) in nodes.items() if not inputs}
    lossy = not lossless(settings, sources)
    out: dict[str, FlowPlan] = {}
    takers: set[str] = set()
    for name in sources:
        images = tuple(key for key in nodes[name][3] if key.endswith("/image"))
        credits = tuple(other for other, (_, _, inputs, _) in nodes.items()
                        if other != name and inputs and _meets(images, inputs))
        takers.update(credits)
        out[name] = FlowPlan(lossless=not lossy, window=settings.window, credits_from=() if lossy else credits)
    for name, (_, _, inputs, _) in nodes.items():
        if name in sources:
            continue
        upstream = tuple(other for other, (_, _, _, outputs) in nodes.items()
                         if other != name and _meets(outputs, inputs))
        out[name] = FlowPlan(lossless=not lossy, window=settings.window, acks=not lossy and name in takers,
                             upstream=upstream)
    return out
