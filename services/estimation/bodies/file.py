"""Bodies files: the rigid bodies of retro-reflective spheres a tracker looks for.

A body is named and holds its sphere centres, metres, in its own frame (the frame its pose
``T_world_body`` is published for). YAML layout::

    bodies:
      - name: wand
        spheres:
          - [-0.065, -0.089, 0.0]
          - [-0.012, 0.046, 0.0]
          - [0.077, 0.043, 0.0]

A file is refused (``BodiesFileError``, one line naming the file, the body and why) when a body has
fewer than three spheres, all its spheres lie on one line, two of its spheres are closer than the
minimum separation, or two bodies share a name. ``check_bodies`` finds what is legal but makes
tracking unreliable (a symmetric body, two bodies alike) or is likely a mistake (a body more than
``MAX_EXTENT`` across: coordinates in millimetres or centimetres) and returns warnings.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Mapping
from pathlib import Path

import numpy as np
import yaml

from services.calibration.yaml_file import read_yaml
from services.estimation.bodies.rigid import DEFAULT_OPTIONS, MatchOptions, body_candidates, pairwise_distances

__all__ = [
    "MAX_EXTENT",
    "MIN_SEPARATION",
    "NAME_PATTERN",
    "BodiesFileError",
    "check_bodies",
    "load_bodies",
    "parse_bodies",
    "save_bodies",
]

NAME_PATTERN = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]*")
"""Body names: one key-expression chunk (the pose is published under the body's name)."""
MIN_SEPARATION = 0.01
"""Default smallest distance (m) between two sphere centres of one body: closer spheres merge into one blob."""
MAX_EXTENT = 2.0
"""Largest plausible distance (m) between two spheres of one body: a body wider than a person is likely given in
millimetres or centimetres."""
UNITS = ((1e-3, "millimetres"), (1e-2, "centimetres"))
"""Units a body's coordinates may have been typed in instead of metres, the likelier first: (metres per unit, name)."""
COLLINEAR_RATIO = 1e-3
"""A body whose centred spheres' second singular value is below this fraction of the first lies on a line."""


class BodiesFileError(ValueError):
    """A bodies file or description that cannot be used; the message names the source, body and reason."""


def load_bodies(path: str | Path, min_separation: float = MIN_SEPARATION) -> dict[str, np.ndarray]:
    """Name -> (N, 3) float64 sphere centres (body frame, m) from the YAML file ``path``, in file order."""
    return parse_bodies(read_yaml(path, BodiesFileError), str(path), min_separation)


def parse_bodies(data: object, source: str = "bodies", min_separation: float = MIN_SEPARATION) -> dict[str, np.ndarray]:
    """The bodies described by ``data`` (the YAML layout, already parsed); errors name ``source``."""
    def fail(where: str, why: str) -> BodiesFileError:
        return BodiesFileError(f"{source}: {where}: {why}")

    if not isinstance(data, dict) or set(data) != {"bodies"}:
        raise fail("top level", "must be a mapping with the single field bodies (a list)")
    entries = data["bodies"]
    if not isinstance(entries, list) or not entries:
        raise fail("bodies", f"must be a non-empty list of {{name, spheres}}, got {entries!r}")
    bodies: dict[str, np.ndarray] = {}
    for n, entry in enumerate(entries):
        where = f"bodies[{n}]"
        if not isinstance(entry, dict) or set(entry) != {"name", "spheres"}:
            raise fail(where, f"must be a mapping with exactly name and spheres, got {entry!r}")
        name = entry["name"]
        if not isinstance(name, str) or not NAME_PATTERN.fullmatch(name):
            raise fail(f"{where}.name", f"must be a word of letters, digits, '_', '.', '-', got {name!r}")
        if name in bodies:
            raise fail(f"{where}.name", f"body {name!r} appears twice")
        bodies[name] = _spheres(entry["spheres"], f"body {name!r}", min_separation, fail)
    return bodies


def _spheres(value: object, where: str, min_separation: float,
             fail: Callable[[str, str], BodiesFileError]) -> np.ndarray:
    """(N, 3) sphere centres of one body's ``spheres`` list, checked."""
    if not isinstance(value, list) or not all(isinstance(row, list) and len(row) == 3 for row in value):
        raise fail(where, f"spheres must be a list of [x, y, z] positions in metres, got {value!r}")
    if not all(isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)
               for row in value for v in row):
        raise fail(where, "sphere positions must be finite numbers (metres)")
    spheres = np.array(value, dtype=np.float64).reshape(-1, 3)
    if len(spheres) < 3:
        raise fail(where, f"has {len(spheres)} sphere(s), a rigid body needs at least 3")
    distances = pairwise_distances(spheres)
    i, j = np.unravel_index(np.argmin(distances + np.diag(np.full(len(spheres), np.inf))), distances.shape)
    if distances[i, j] < min_separation:
        raise fail(where, f"spheres {i} and {j} are {distances[i, j] * 1e3:.1f} mm apart, closer than the "
                          f"minimum {min_separation * 1e3:.1f} mm")
    extent = np.linalg.svd(spheres - spheres.mean(axis=0), compute_uv=False)
    if extent[1] < COLLINEAR_RATIO * extent[0]:
        raise fail(where, "all spheres lie on one line, which leaves the rotation about it undetermined")
    return spheres


def save_bodies(path: str | Path, bodies: Mapping[str, np.ndarray]) -> None:
    """Write name -> (N, 3) sphere centres (body frame, m) as a bodies file (checked as ``parse_bodies`` does)."""
    document = {"bodies": [{"name": name, "spheres": np.asarray(spheres, dtype=np.float64).tolist()}
                           for name, spheres in bodies.items()]}
    parse_bodies(document, str(path))
    Path(path).write_text(yaml.safe_dump(document, sort_keys=False, default_flow_style=None))


def check_bodies(bodies: Mapping[str, np.ndarray], options: MatchOptions = DEFAULT_OPTIONS) -> list[str]:
    """Warnings (one line each, empty when none) about bodies the matcher could confuse.

    ``bodies``: name -> (N, 3) float64 sphere centres, body frame. Judged with the matcher's own
    tolerances (``options``): a body is symmetric when its spheres, all seen or (for N >= 4 with
    ``allow_missing``) with any one hidden, admit more than one assignment whose distances agree and
    whose rigid fit passes the gate; two bodies are alike when one can be matched on the other's spheres
    (from three of its spheres or more, as the search finds a body).
    """
    warnings = []
    for name, spheres in bodies.items():
        spheres = np.asarray(spheres, dtype=np.float64)
        extent = float(pairwise_distances(spheres).max())
        if extent > MAX_EXTENT:
            warnings.append(f"body {name!r} is {extent:.3g} m across (at most {MAX_EXTENT:g} m is plausible): "
                            f"{unit_mistake(extent)}")
        views = [("all spheres seen", spheres, len(spheres))]
        if options.allow_missing and len(spheres) >= 4:
            views += [(f"sphere {k} hidden", np.delete(spheres, k, axis=0), len(spheres) - 1)
                      for k in range(len(spheres))]
        for label, points, count in views:
            fits = [c for c in body_candidates(spheres, points, options) if c.fit.count == count]
            if len(fits) > 1:
                warnings.append(f"body {name!r} is symmetric ({label}): {len(fits)} sphere assignments fit, "
                                f"its orientation is ambiguous")
    for name, spheres in bodies.items():
        for other, other_spheres in bodies.items():
            if other == name:
                continue
            found = body_candidates(spheres, other_spheres, options)
            if found:
                warnings.append(f"body {name!r} is too like body {other!r}: it fits {other!r}'s spheres "
                                f"{found[0].used.tolist()} to {found[0].fit.residual_rms * 1e3:.1f} mm RMS")
    return warnings


def unit_mistake(extent: float) -> str:
    """The likely unit mistake of a body ``extent`` m across (more than ``MAX_EXTENT``), said to the user."""
    for scale, unit in UNITS:
        if 10 * MIN_SEPARATION <= extent * scale <= MAX_EXTENT:
            return (f"were its coordinates typed in {unit}? It would be {extent * scale:.3g} m across; a bodies "
                    f"file is in metres")
    return "a bodies file is in metres"
