"""Node kinds and trackers, found where they are declared: no table lists them.

The launcher searches the ``services`` package and every package named in ``ARTRACK_PLUGINS``
(comma-separated importable names, e.g. ``ARTRACK_PLUGINS=mytracker``):

* a node kind is the ``KIND = NodeKind(name="...", ...)`` of a module called ``node.py`` or
  ``*_node.py`` (``services.runtime.kind``). Modules are read, not imported, to learn the
  names; only a kind in use is imported.
* a tracker is a ``trackers/NAME.toml`` pipeline template (``services.launcher.tracker``).

Two declarations of one name are refused, naming both places.
"""

from __future__ import annotations

import ast
import functools
import importlib
import importlib.util
import os
from dataclasses import dataclass
from pathlib import Path

from services.runtime.kind import NodeKind

PLUGINS_ENV = "ARTRACK_PLUGINS"
BUILT_IN = "services"


class DiscoveryError(ValueError):
    """A plug-in package that cannot be searched, or a name declared twice."""


@dataclass(frozen=True)
class Catalogue:
    """What the search found: kind name -> module, tracker name -> template file."""

    kinds: dict[str, str]
    trackers: dict[str, Path]


def search_roots(environ: dict[str, str] | None = None) -> tuple[str, ...]:
    """``services`` and the packages named in ``ARTRACK_PLUGINS``, in that order."""
    text = (os.environ if environ is None else environ).get(PLUGINS_ENV, "")
    return (BUILT_IN, *(name.strip() for name in text.split(",") if name.strip()))


def declared_kind(path: Path) -> str | None:
    """The literal ``name`` of a module-level ``KIND = NodeKind(...)`` in ``path``, if any."""
    for statement in ast.parse(path.read_text(), str(path)).body:
        if not (isinstance(statement, ast.Assign) and isinstance(statement.value, ast.Call)):
            continue
        if not any(isinstance(t, ast.Name) and t.id == "KIND" for t in statement.targets):
            continue
        for keyword in statement.value.keywords:
            if keyword.arg == "name" and isinstance(keyword.value, ast.Constant):
                return str(keyword.value.value)
        raise DiscoveryError(f"{path}: KIND must be NodeKind(name=\"...\", ...) with the name as a string literal")
    return None


def _package_dirs(root: str) -> list[Path]:
    try:
        spec = importlib.util.find_spec(root)
    except (ImportError, ValueError) as exc:
        raise DiscoveryError(f"{PLUGINS_ENV}: cannot import {root!r}: {exc}") from exc
    if spec is None or not spec.submodule_search_locations:
        raise DiscoveryError(f"{PLUGINS_ENV}: {root!r} is not an importable package")
    return [Path(p) for p in spec.submodule_search_locations]


def _add(found: dict, name: str, where: object, what: str) -> None:
    if name in found and found[name] != where:
        raise DiscoveryError(f"{what} {name!r} is declared twice: in {found[name]} and in {where}")
    found[name] = where


@functools.cache
def catalogue(roots: tuple[str, ...] | None = None) -> Catalogue:
    """Search ``roots`` (default ``search_roots()``) for node kinds and trackers."""
    kinds: dict[str, str] = {}
    trackers: dict[str, Path] = {}
    for root in roots or search_roots():
        for directory in _package_dirs(root):
            for path in sorted(directory.rglob("*.py")):
                if path.name != "node.py" and not path.name.endswith("_node.py"):
                    continue
                name = declared_kind(path)
                if name is not None:
                    module = ".".join((root, *path.relative_to(directory).with_suffix("").parts))
                    _add(kinds, name, module, "node kind")
            for path in sorted(directory.rglob("trackers/*.toml")):
                _add(trackers, path.stem, path, "tracker")
    return Catalogue(kinds, trackers)


def kind(name: str) -> NodeKind:
    """The node kind called ``name`` (its module imported now); ValueError listing the known kinds otherwise."""
    modules = catalogue().kinds
    if name not in modules:
        raise ValueError(f"unknown node kind {name!r} (known: {', '.join(sorted(modules))})")
    declared = getattr(importlib.import_module(modules[name]), "KIND", None)
    if not isinstance(declared, NodeKind) or declared.name != name:
        raise DiscoveryError(f"{modules[name]}: KIND is not a NodeKind named {name!r}")
    return declared
