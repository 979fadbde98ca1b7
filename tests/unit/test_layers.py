"""The house plan's import rules, read from every module's imports (docs/architecture.md).

A room is a top-level package under ``protocol`` or ``services`` (``services.bus``,
``services.geometry``, ``services.cli``, ...); ``services/convert.py`` is a room of its own.
Imports inside a function count like any other: a rule holds for the whole module.
"""

from __future__ import annotations

import ast
from collections import defaultdict
from functools import cache
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
OURS = ("protocol", "services")
ALGORITHM_ROOMS = ("geometry", "calibration", "capture", "synthetic", "detection", "estimation", "slam")
"""Rooms of pure algorithms, but for their node modules (``node.py``, ``*_node.py``)."""
BUS_SIDE = ("zenoh", "protocol", "services.bus", "services.runtime", "services.launcher", "services.client")


def module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


@cache
def modules() -> dict[str, frozenset[str]]:
    """Every module of ours -> the absolute names it imports."""
    found = {}
    for top in OURS:
        for path in sorted((ROOT / top).rglob("*.py")):
            imported = set()
            for node in ast.walk(ast.parse(path.read_text(), str(path))):
                if isinstance(node, ast.Import):
                    imported.update(alias.name for alias in node.names)
                elif isinstance(node, ast.ImportFrom):
                    assert node.level == 0, f"{path}: relative import; the rules read absolute names"
                    imported.add(node.module or "")
                    imported.update(f"{node.module}.{alias.name}" for alias in node.names)
            found[module_name(path)] = frozenset(imported)
    return found


def room(name: str) -> str | None:
    """The room of a module name of ours (``services.bus.pubsub`` -> ``services.bus``); None if not ours."""
    parts = name.split(".")
    if parts[0] == "protocol":
        return "protocol"
    if parts[0] == "services" and len(parts) > 1:
        return f"services.{parts[1]}"
    return None


def within(name: str, prefixes: tuple[str, ...]) -> bool:
    return any(name == p or name.startswith(p + ".") for p in prefixes)


def offences(prefix: str, allowed: tuple[str, ...], *, skip_nodes: bool = False) -> list[str]:
    """``module -> import`` pairs of modules under ``prefix`` importing ours outside ``allowed``."""
    bad = []
    for module, imported in modules().items():
        is_node = module.rsplit(".", 1)[-1] == "node" or module.endswith("_node")
        if not within(module, (prefix,)) or (skip_nodes and is_node):
            continue
        for name in sorted(imported):
            if room(name) is not None and not within(name, allowed):
                bad.append(f"{module} -> {name}")
    return bad


def test_the_rules_see_every_room():
    rooms = {room(m) for m in modules()}
    assert {"protocol", "services.bus", "services.runtime", "services.launcher", "services.client",
            "services.geometry", "services.calibration"} <= rooms


def test_protocol_imports_nothing_of_ours():
    assert offences("protocol", ("protocol",)) == []


def test_geometry_imports_nothing_of_ours():
    assert offences("services.geometry", ("services.geometry",)) == []


@pytest.mark.parametrize("algorithms", ALGORITHM_ROOMS)
def test_algorithms_never_touch_the_bus_or_the_wire(algorithms):
    bad = []
    for module, imported in modules().items():
        if not within(module, (f"services.{algorithms}",)):
            continue
        if module.rsplit(".", 1)[-1] == "node" or module.endswith("_node"):
            continue
        bad += [f"{module} -> {name}" for name in sorted(imported) if within(name, BUS_SIDE)]
    assert bad == []


def test_scenes_stand_on_geometry_and_the_marker_dictionaries_alone():
    allowed = ("services.synthetic", "services.geometry", "services.detection.markers.detector")
    assert offences("services.synthetic", allowed) == []


@pytest.mark.parametrize("room_name", ["detection", "estimation", "slam", "recorder"])
def test_no_tracker_nor_the_recorder_knows_sources_or_scenes(room_name):
    """Trackers are told what a scene holds through their options (the job assembly writes its fixture files)."""
    bad = [f"{m} -> {n}" for m, imported in modules().items() if within(m, (f"services.{room_name}",))
           for n in sorted(imported) if within(n, ("services.synthetic", "services.capture"))]
    assert bad == []


def test_the_bus_knows_nothing_of_nodes():
    assert offences("services.bus", ("protocol", "services.bus")) == []


def test_the_runtime_imports_no_service_launcher_or_client():
    assert offences("services.runtime", ("protocol", "services.bus", "services.runtime")) == []


def test_the_client_library_stands_on_the_bus():
    allowed = ("protocol", "services.bus", "services.client", "services.geometry", "services.convert")
    assert offences("services.client", allowed) == []


def test_nothing_below_sits_on_the_launcher_or_the_command_line():
    top = ("services.launcher", "services.cli")
    bad = [f"{m} -> {n}" for m, imported in modules().items() if not within(m, top)
           for n in sorted(imported) if within(n, top)]
    assert bad == []


def find_cycle(edges: dict[str, set[str]]) -> list[str] | None:
    """A cycle of ``edges`` (room -> rooms it imports) as the rooms along it, or None."""
    state: dict[str, str] = {}

    def visit(node: str, path: list[str]) -> list[str] | None:
        state[node] = "open"
        for nxt in sorted(edges.get(node, ())):
            if state.get(nxt) == "open":
                return [*path, node, nxt]
            if nxt not in state and (found := visit(nxt, [*path, node])):
                return found
        state[node] = "done"
        return None

    for start in sorted(edges):
        if start not in state and (found := visit(start, [])):
            return found
    return None


def test_no_circular_imports_between_rooms():
    edges: dict[str, set[str]] = defaultdict(set)
    for module, imported in modules().items():
        for name in imported:
            if room(name) is not None and room(name) != room(module):
                edges[str(room(module))].add(str(room(name)))
    assert find_cycle(edges) is None


def test_the_cycle_search_finds_a_cycle_and_accepts_a_tree():
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b", "c"}, "b": {"c"}, "c": set()}) is None
