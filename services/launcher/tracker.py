"""Trackers: pipeline templates that ``artrack run TRACKER`` fills from a source and flags.

A tracker is a TOML file ``trackers/NAME.toml`` in any package the launcher searches
(``services.launcher.kinds``)::

    summary = "ArUco/AprilTag detection -> marker and board poses per camera"

    [nodes."marker-{camera}"]   # a name holding {camera}: one node per camera of the source
    kind = "marker_pose"
    camera = "{camera}"         # string values may hold {camera} too

    [nodes.bodies]              # one node for the whole rig
    kind = "rigid_bodies"
    cameras = "{cameras}"       # a value "{cameras}" is the list of the source's cameras

    [source]                    # optional: the source node's place
    process = "rig"             # run it in process "rig", with the nodes that name it too

A template lists the nodes downstream of the source; the source node (capture or replay)
and the recorder and viewer are added by the job. A node's ``process`` (which may hold
``{camera}``) groups it with the others naming the same process (``services.launcher.pipeline``):
the grouping the tracker's rate needs, which ``artrack run --processes`` and ``--process`` change.

Its flags are generated from the parameter models of its node kinds (``services.launcher.flags``):
every flat parameter but those the template binds to ``{camera}``. A field shared by several kinds
is one flag when its type is the same in all of them; a flag set on the command line applies to
every node having that field.
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ValidationError

from services.launcher.flags import Flag, explain, flags_for
from services.launcher.kinds import catalogue, kind
from services.launcher.pipeline import RESERVED, NodeSpec, PipelineError
from services.runtime.params import flat_fields

CAMERA = "{camera}"
CAMERAS = "{cameras}"


@dataclass(frozen=True)
class Tracker:
    """A loaded template: its name, summary and node tables (values as written, ``{camera}`` unfilled)."""

    name: str
    summary: str
    path: Path
    nodes: dict[str, dict[str, Any]]
    source_process: str | None = None

    @classmethod
    def load(cls, name: str) -> Tracker:
        """The tracker called ``name``; ValueError listing the known ones, PipelineError for a bad file."""
        found = catalogue().trackers
        if name not in found:
            raise ValueError(f"unknown tracker {name!r} (known: {', '.join(sorted(found))})")
        path = found[name]
        try:
            document = tomllib.loads(path.read_text())
        except tomllib.TOMLDecodeError as exc:
            raise PipelineError(f"{path}: not valid TOML: {exc}") from exc
        nodes = document.get("nodes", {})
        if not isinstance(nodes, dict) or not all(isinstance(t, dict) and "kind" in t for t in nodes.values()):
            raise PipelineError(f"{path}: each [nodes.NAME] table needs a kind")
        unknown = set(document) - {"summary", "nodes", "source"}
        if unknown:
            raise PipelineError(f"{path}: unknown top-level key(s) {', '.join(sorted(unknown))} (summary, nodes, "
                                f"source)")
        source = document.get("source", {})
        if not isinstance(source, dict) or set(source) - {"process"}:
            raise PipelineError(f"{path}: [source] may only say the source's process")
        return cls(name, str(document.get("summary", "")), path, nodes, source.get("process"))

    def layout(self) -> str:
        """The template's processes in one line: who runs with whom (``{camera}`` left as written)."""
        groups: dict[str, list[str]] = {}
        if self.source_process is not None:
            groups[self.source_process] = ["the source"]
        for name, table in self.nodes.items():
            groups.setdefault(table.get("process") or name, []).append(name)
        return "; ".join(f"process {process}: {', '.join(names)}" if names != [process] else f"{process} alone"
                         for process, names in groups.items())

    def models(self) -> list[tuple[str, type[BaseModel], set[str]]]:
        """``(kind, Params, fields bound by the template)`` of each distinct node kind, in template order."""
        seen: dict[str, tuple[str, type[BaseModel], set[str]]] = {}
        for table in self.nodes.values():
            bound = {key for key, value in table.items() if key in RESERVED or isinstance(value, str) and (
                CAMERA in value or value == CAMERAS)}
            name = table["kind"]
            model = kind(name).params
            if name in seen:
                seen[name][2].update(bound)
            else:
                seen[name] = (name, model, bound)
        return list(seen.values())

    def flags(self, taken: dict[str, Flag]) -> list[Flag]:
        """The template's flags; a field that ``taken`` (the source's flags) already has with another
        type gets the option ``--<kind>-<field>`` instead of ``--<field>``."""
        chosen: dict[str, Flag] = {}
        for kind_name, model, bound in self.models():
            for flag in flags_for(model, bound | {"camera"}):
                clash = taken.get(flag.field) or chosen.get(flag.field)
                if clash is None:
                    chosen[flag.field] = flag
                elif clash.info.annotation != flag.info.annotation:
                    renamed = replace(flag, option=f"--{kind_name}-{flag.field}".replace("_", "-"), owner=kind_name)
                    chosen[renamed.key] = renamed
        return list(chosen.values())

    def expand(self, cameras: list[str], options: dict[str, Any], flags: list[Flag]) -> dict[str, NodeSpec]:
        """The template's nodes for ``cameras`` with ``options`` (``{field or kind.field: value}``) applied.

        Raises ValueError naming the flag when a value does not validate.
        """
        nodes: dict[str, NodeSpec] = {}
        for name, table in self.nodes.items():
            for camera in cameras if CAMERA in name else [None]:
                values: dict[str, Any] = {k: list(cameras) if v == CAMERAS else
                                          v.replace(CAMERA, camera) if camera and isinstance(v, str) else v
                                          for k, v in table.items()}
                node_kind = kind(values["kind"])
                fields = flat_fields(node_kind.params)
                for key, value in options.items():
                    owner, _, field = key.rpartition(".")
                    if field in fields and owner in ("", node_kind.name) and field not in values:
                        values[field] = value
                params = {k: v for k, v in values.items() if k not in RESERVED}
                try:
                    node_kind.validate(params)
                except ValidationError as exc:
                    raise ValueError(explain(exc, flags, f"tracker {self.name}, node {name}")) from exc
                place = {k: values[k] for k in RESERVED if k != "kind" and k in values}
                nodes[name.replace(CAMERA, camera) if camera else name] = NodeSpec(kind=node_kind.name, **place,
                                                                                   **params)
        return nodes
