"""A synthetic scene's fixtures as the files trackers read, and the tracker options that name them.

A scene gives its fixtures as data (``services.synthetic.fixtures``); each is written here by the
room that owns its format, into a folder:

    bodies.yaml                 the rigid bodies (``services.estimation.bodies.file``)
    targets/<name>.npz, .png    the image target, a target library (``services.estimation.targets.library``)
    marker_map.yaml             the marker map (``services.estimation.markers.map``)
    rig.yaml                    every camera (``services.calibration.rig``), for scenes of two or more

``write_fixtures`` writes them (``artrack scene export`` writes its folder so). For ``artrack run``,
``scene_settings`` says what a synthetic source settles of a tracker's options: the scene's plain
settings (a markers scene's ``marker_length`` and ``dictionary``), its bodies file as ``bodies``, its
target as ``target`` in the library ``targets``; ``scene_target_library`` turns ``--target
synthetic:SCENE[?name=value&...]`` into the same. A job's files go to ``fixture_folder(scene,
options)``, ``$XDG_CACHE_HOME/artrack/scenes/<scene>-<digest of its options>`` (else under
``~/.cache``): written afresh for every job, each file moved into place whole (jobs of one scene may
run side by side), and kept, so a pipeline saved with ``--save-pipeline`` finds them later.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
import tempfile
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

from services.synthetic import Fixtures, scene_fixtures, scene_options

__all__ = ["BODIES_FILE", "MARKER_MAP_FILE", "RIG_FILE", "SCENE_PREFIX", "TARGETS_FOLDER", "FixtureFiles",
           "Settled", "fixture_folder", "scene_settings", "scene_target_library", "write_fixtures"]

SCENE_PREFIX = "synthetic:"
BODIES_FILE = "bodies.yaml"
TARGETS_FOLDER = "targets"
MARKER_MAP_FILE = "marker_map.yaml"
RIG_FILE = "rig.yaml"
FIXTURES = ("bodies", "target", "marker_map", "rig")
"""What ``write_fixtures`` may write, by ``Fixtures`` field."""

log = logging.getLogger("artrack")


@dataclass
class FixtureFiles:
    """What ``write_fixtures`` wrote (None where the scene has no such fixture or it was not asked for);
    ``notes``: one line per fixture the scene has whose file cannot be written, saying why."""

    bodies: Path | None = None
    targets: Path | None = None
    marker_map: Path | None = None
    rig: Path | None = None
    notes: list[str] = field(default_factory=list)


def write_fixtures(folder: Path, fixtures: Fixtures, which: tuple[str, ...] = FIXTURES) -> FixtureFiles:
    """Write the fixtures named in ``which`` (of ``FIXTURES``) that the scene has into ``folder`` (made when absent).

    Bodies a bodies file refuses (``ir_rig``'s wand: its spheres lie on one line) are left out, with a note."""
    from services.calibration.rig import Rig, write_rig
    from services.estimation.bodies.file import BodiesFileError, save_bodies
    from services.estimation.markers.map import map_from_poses, save_marker_map
    from services.estimation.targets.library import TargetLibrary, write_target
    from services.estimation.targets.target import build_target

    folder.mkdir(parents=True, exist_ok=True)
    done = FixtureFiles()
    if "bodies" in which and fixtures.bodies:
        try:
            save_bodies(folder / BODIES_FILE, fixtures.bodies)
            done.bodies = folder / BODIES_FILE
        except BodiesFileError as exc:
            done.notes.append(f"no bodies file: {exc}")
    if "target" in which and fixtures.target is not None:
        target = fixtures.target
        library = TargetLibrary(folder / TARGETS_FOLDER)
        library.folder.mkdir(exist_ok=True)
        write_target(build_target(target.name, target.image, target.width_m), library.path(target.name),
                     f"{SCENE_PREFIX}{fixtures.scene}")
        done.targets = library.folder
    if "marker_map" in which and fixtures.marker_map is not None:
        layout = fixtures.marker_map
        save_marker_map(folder / MARKER_MAP_FILE,
                        map_from_poses(layout.name, layout.poses, layout.length, layout.dictionary))
        done.marker_map = folder / MARKER_MAP_FILE
    if "rig" in which and len(fixtures.rig) >= 2:
        write_rig(folder / RIG_FILE, Rig(fixtures.scene, fixtures.rig))
        done.rig = folder / RIG_FILE
    return done


def fixture_folder(scene: str, options: Mapping[str, object]) -> Path:
    """Where a job's fixture files of ``scene`` built with ``options`` (typed values) go (module docstring)."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    text = json.dumps({"scene": scene, "options": dict(options)}, sort_keys=True, default=str)
    return Path(base) / "artrack" / "scenes" / f"{scene}-{hashlib.sha256(text.encode()).hexdigest()[:16]}"


def _job_fixtures(fixtures: Fixtures, options: Mapping[str, object], which: tuple[str, ...]) -> FixtureFiles:
    """``write_fixtures`` into the job folder of the scene, through a folder of this job's own: each file is
    moved into place whole, so another job of the same scene never reads one half written."""
    folder = fixture_folder(fixtures.scene, options)
    folder.mkdir(parents=True, exist_ok=True)
    own = Path(tempfile.mkdtemp(prefix=".writing-", dir=folder))

    def moved(path: Path | None) -> Path | None:
        return None if path is None else folder / path.relative_to(own)

    try:
        written = write_fixtures(own, fixtures, which)
        for path in sorted(own.rglob("*"), key=lambda p: len(p.parts)):
            if path.is_dir():
                (folder / path.relative_to(own)).mkdir(exist_ok=True)
            else:
                os.replace(path, folder / path.relative_to(own))
    finally:
        shutil.rmtree(own, ignore_errors=True)
    return FixtureFiles(moved(written.bodies), moved(written.targets), moved(written.marker_map), moved(written.rig),
                        [note.replace(str(own), str(folder)) for note in written.notes])


@dataclass(frozen=True)
class Settled:
    """Tracker options a synthetic source ``uri`` settles together: ``fields``, whose values ``values()`` gives
    (writing the files they name)."""

    uri: str
    fields: tuple[str, ...]
    values: Callable[[], dict[str, Any]]
    """The fields' values, or nothing when the scene cannot give them after all (said in one line)."""


def scene_settings(uris: tuple[str, ...] | list[str], options: Mapping[str, object]) -> list[Settled]:
    """What the synthetic sources among ``uris`` (built with scene ``options``, typed values) settle of a
    tracker's options: each plain setting on its own, the bodies file as ``bodies``, the target as ``target``
    with its library ``targets``. Other sources settle nothing. ValueError naming a scene that cannot be built."""
    settled: list[Settled] = []
    for uri in uris:
        if not uri.startswith(SCENE_PREFIX):
            continue
        try:
            fixtures = scene_fixtures(uri.removeprefix(SCENE_PREFIX), **options)
        except ValueError as exc:
            raise ValueError(f"{uri}: {exc}") from exc
        settled += [Settled(uri, (name,), partial(dict, {name: value})) for name, value in fixtures.settings.items()]
        if fixtures.bodies:
            settled.append(Settled(uri, ("bodies",), partial(_bodies, fixtures, options)))
        if fixtures.target is not None:
            settled.append(Settled(uri, ("target", "targets"), partial(_target, fixtures, options)))
    return settled


def _bodies(fixtures: Fixtures, options: Mapping[str, object]) -> dict[str, Any]:
    """``bodies``: the scene's bodies file; nothing, said in one line, when a bodies file refuses them."""
    written = _job_fixtures(fixtures, options, ("bodies",))
    for note in written.notes:
        log.info("%s%s: %s", SCENE_PREFIX, fixtures.scene, note)
    return {} if written.bodies is None else {"bodies": str(written.bodies)}


def _target(fixtures: Fixtures, options: Mapping[str, object]) -> dict[str, Any]:
    """``target`` and ``targets``: the scene's target, in a library of its own."""
    assert fixtures.target is not None
    written = _job_fixtures(fixtures, options, ("target",))
    return {"target": (fixtures.target.name,), "targets": str(written.targets)}


def scene_target_library(names: list[str] | tuple[str, ...], library_given: bool) -> dict[str, Any] | None:
    """``target`` and ``targets`` for targets named ``synthetic:SCENE[?name=value&...]`` (a scene's own, built
    with the options after ``?``, values as text converted by their types): the scene's target in a library of
    its own. None when no name is a scene's. ValueError naming the fault: a URI that is not valid, a scene that
    renders no image target, or a scene's target named beside other targets or a library (``library_given``),
    as the node reads one library."""
    scenes = [name for name in names if name.startswith(SCENE_PREFIX)]
    if not scenes:
        return None
    if len(names) > 1 or library_given:
        raise ValueError(f"target {scenes[0]!r}: a scene's target is tracked alone (no other target, no target "
                         f"library); to track it beside others, copy the targets/ folder `artrack scene export` "
                         f"writes into the library")
    scene, options = _parse(scenes[0])
    fixtures = scene_fixtures(scene, **options)
    if fixtures.target is None:
        raise ValueError(f"target {scenes[0]!r}: scene {scene!r} renders no image target (planar_target does)")
    return _target(fixtures, options)


def _parse(uri: str) -> tuple[str, dict[str, object]]:
    """``(scene, options)`` of a scene target URI, options converted by their types; ValueError naming the fault."""
    scene, _, query = uri.removeprefix(SCENE_PREFIX).partition("?")
    texts: dict[str, object] = {}
    for pair in filter(None, query.split("&")):
        name, sep, value = pair.partition("=")
        if not sep or not name:
            raise ValueError(f"target {uri!r}: write scene options as name=value, got {pair!r}")
        texts[name] = value
    try:
        return scene, scene_options(scene, texts)
    except ValueError as exc:
        raise ValueError(f"target {uri!r}: {exc}") from exc
