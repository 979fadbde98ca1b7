"""The house plan's import rules, read from every module's imports (docs/architecture.md).

A room is a top-level package under ``protocol`` or ``services`` (``services.bus``,
``services.geometry``, ``services.cli``, ...); ``services/convert.py`` is a room of its own.
Imports inside a function count like any other: a rule holds for the whole module. A node module
is one that declares a node kind (``KIND = NodeKind(...)``, read as the launcher reads it), whatever
its name; every other module of an algorithm room is an algorithm.

The rooms drawing of docs/architecture.md is held against the code: each arrow is a room that imports
another, dotted when only node modules do. ``python -m tests.unit.test_layers`` prints it from the code.
"""

from __future__ import annotations

import ast
import re
from collections import defaultdict
from functools import cache
from pathlib import Path

import pytest

from services.launcher.kinds import declared_kind

ROOT = Path(__file__).resolve().parents[2]
OURS = ("protocol", "services")
ALGORITHM_ROOMS = ("geometry", "calibration", "capture", "synthetic", "detection", "estimation", "slam")
"""Rooms of pure algorithms, but for their node modules (those that declare ``KIND``)."""
BUS_SIDE = ("zenoh", "protocol", "services.bus", "services.runtime", "services.launcher", "services.client")
DOC = ROOT / "docs" / "architecture.md"
MARK = "%% rooms: python -m tests.unit.test_layers"
"""The comment that marks the rooms drawing among the page's mermaid blocks."""
SOLID, DOTTED = "-->", "-.->"
"""A room's modules import another room; only its node modules do."""
VOCABULARY = ("protocol.tracking_state",)
"""What of ``protocol`` algorithms may import: the tracking states they report in (standard library only)."""


def module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def sources() -> list[Path]:
    """Every module file of ours."""
    return [path for top in OURS for path in sorted((ROOT / top).rglob("*.py"))]


@cache
def modules() -> dict[str, frozenset[str]]:
    """Every module of ours -> the absolute names it imports."""
    found = {}
    for path in sources():
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


@cache
def node_modules() -> frozenset[str]:
    """The modules that declare a node kind: a module-level ``KIND = NodeKind(name="...", ...)``."""
    return frozenset(module_name(path) for path in sources() if declared_kind(path) is not None)


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


def offences(prefix: str, allowed: tuple[str, ...]) -> list[str]:
    """``module -> import`` pairs of modules under ``prefix`` importing ours outside ``allowed``."""
    bad = []
    for module, imported in modules().items():
        if not within(module, (prefix,)):
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
        if not within(module, (f"services.{algorithms}",)) or module in node_modules():
            continue
        bad += [f"{module} -> {name}" for name in sorted(imported)
                if within(name, BUS_SIDE) and not within(name, VOCABULARY)]
    assert bad == []


def test_the_vocabulary_algorithms_share_with_the_wire_imports_only_the_standard_library():
    for name in VOCABULARY:
        assert modules()[name] <= {"__future__", "__future__.annotations", "enum", "enum.StrEnum"}, name


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


def room_imports() -> dict[tuple[str, str], bool]:
    """``(importer, imported)`` for each room that imports another -> whether node modules alone do."""
    nodes_only: dict[tuple[str, str], bool] = {}
    for module, imported in modules().items():
        for name in imported:
            pair = (str(room(module)), str(room(name)))
            if room(name) is not None and pair[0] != pair[1]:
                nodes_only[pair] = nodes_only.get(pair, True) and module in node_modules()
    return nodes_only


def test_no_circular_imports_between_rooms():
    edges: dict[str, set[str]] = defaultdict(set)
    for importer, imported in room_imports():
        edges[importer].add(imported)
    assert find_cycle(edges) is None


def test_the_cycle_search_finds_a_cycle_and_accepts_a_tree():
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b", "c"}, "b": {"c"}, "c": set()}) is None


def box(name: str) -> str:
    """A room's box in the drawing: ``services.bus`` -> ``bus``, ``protocol`` stays."""
    return name.removeprefix("services.")


def arrows(imports: dict[tuple[str, str], bool]) -> set[str]:
    """``room_imports()`` as the drawing's arrows, one a pair: ``"cli --> launcher"``, ``"echo -.-> runtime"``."""
    return {f"{box(importer)} {DOTTED if nodes_only else SOLID} {box(imported)}"
            for (importer, imported), nodes_only in imports.items()}


def drawing(imports: dict[tuple[str, str], bool]) -> str:
    """The rooms drawing of ``imports``, a mermaid block: one line per importing room and kind of arrow."""
    rows: dict[tuple[str, str], list[str]] = defaultdict(list)
    for (importer, imported), nodes_only in sorted(imports.items()):
        rows[(box(importer), DOTTED if nodes_only else SOLID)].append(box(imported))
    lines = [f"    {importer} {arrow} {' & '.join(boxes)}" for (importer, arrow), boxes in sorted(rows.items())]
    return "\n".join(["```mermaid", "flowchart TD", f"    {MARK}", *lines, "```"])


def drawn_arrows(page: str) -> set[str]:
    """The arrows of the rooms drawing on ``page`` (markdown): the mermaid block holding ``MARK``."""
    blocks = [block for block in re.findall(r"^```mermaid\n(.*?)^```$", page, re.DOTALL | re.MULTILINE)
              if MARK in block]
    assert len(blocks) == 1, f"{len(blocks)} mermaid blocks hold {MARK!r}; the rooms drawing is one"
    found = set()
    for line in blocks[0].splitlines()[1:]:
        if not line.strip() or line.strip() == MARK:
            continue
        match = re.fullmatch(r"\s*(\w+) (-->|-\.->) (\w+(?: & \w+)*)", line)
        assert match, f"not an arrow of the rooms drawing: {line!r}"
        found |= {f"{match[1]} {match[2]} {target}" for target in match[3].split(" & ")}
    return found


def test_the_rooms_drawing_has_every_import_between_rooms_and_no_other():
    code, doc = arrows(room_imports()), drawn_arrows(DOC.read_text())
    assert (sorted(code - doc), sorted(doc - code)) == ([], []), (
        f"{DOC.name}'s rooms drawing misses {sorted(code - doc)} and draws {sorted(doc - code)} that the code "
        "lacks; python -m tests.unit.test_layers prints the drawing of the code")


def test_the_drawing_reads_back_as_drawn():
    imports = {("services.cli", "services.bus"): False, ("services.cli", "protocol"): False,
               ("services.echo", "services.runtime"): True}
    assert drawn_arrows(f"text\n\n{drawing(imports)}\n") == arrows(imports) == {
        "cli --> bus", "cli --> protocol", "echo -.-> runtime"}


def test_every_node_kind_is_where_the_launcher_looks():
    assert [m for m in sorted(node_modules()) if m.rsplit(".", 1)[-1] != "node" and not m.endswith("_node")] == []


if __name__ == "__main__":
    print(drawing(room_imports()))
