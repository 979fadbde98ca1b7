"""Marker maps: several markers rigidly placed in one common frame, tracked as a single target.

A map named ``name`` holds, per marker id, its side length (metres, the black square) and its
pose ``T_map_marker`` (4, 4). Marker frames are ArUco's: origin at the marker centre, x right,
y up, z out of the marker. The estimator publishes the map's pose as ``T_camera_<name>``.

YAML layout (one of ``markers`` or ``grid``; ``dictionary`` is optional, a cv2.aruco name such
as ``DICT_4X4_50``, and when given every id must exist in it)::

    name: table
    dictionary: DICT_4X4_50
    markers:
      - {id: 3, length: 0.05, position: [0.0, 0.0, 0.0], quaternion: [0, 0, 0, 1]}
      - {id: 8, length: 0.10, position: [0.3, 0.0, 0.0]}

    # or
    name: board
    grid: {columns: 3, rows: 2, length: 0.05, separation: 0.05, first_id: 0}

``position`` is in metres in the map frame; ``quaternion`` (x, y, z, w), optional (identity),
must be of unit norm within 1e-3 and is normalised. A grid is laid out like the synthetic
``markers`` scene's board: ids ``first_id, first_id + 1, ...`` row by row from the top left,
``separation`` metres of gap between neighbouring markers as in OpenCV's GridBoard (centre
spacing ``length + separation``), the map frame at the centre of the grid, x right, y up, z out
of the board. The last example is the default scene's board. Every error in a file is a
MarkerMapError naming the file, the field and why.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import yaml

from services.calibration.yaml_file import read_yaml
from services.geometry.rotation import matrix_from_quaternion, quaternion_from_matrix
from services.geometry.se3 import make_transform, transform_points

NAME_PATTERN = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]*")
"""Map names: one key-expression chunk, so never ``marker/<id>``."""
MAX_GRID_MARKERS = 1000
"""The largest ArUco dictionaries hold 1000 markers."""


class MarkerMapError(ValueError):
    """A marker map file or description that cannot be used; the message names the source and field."""


Fail = Callable[[str, str], MarkerMapError]
"""``fail(where, why)``: the error for field ``where`` of the source being parsed."""


def marker_corners(length: float) -> np.ndarray:
    """(4, 3) corners of a marker of side ``length`` in its own frame, ArUco order TL, TR, BR, BL."""
    h = length / 2
    return np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])


@dataclass(frozen=True)
class MapMarker:
    """One marker of a map: ``length`` metres, pose ``T_map_marker`` (4, 4)."""

    id: int
    length: float
    T_map_marker: np.ndarray

    def corners(self) -> np.ndarray:
        """(4, 3) corners in the map frame, ArUco order TL, TR, BR, BL."""
        return transform_points(self.T_map_marker, marker_corners(self.length))


@dataclass(frozen=True)
class MarkerMap:
    """A named set of markers in one frame: ``markers`` id -> MapMarker; ``dictionary`` optional."""

    name: str
    markers: Mapping[int, MapMarker] = field(default_factory=dict)
    dictionary: str | None = None


def map_from_poses(name: str, poses: Mapping[int, np.ndarray], length: float,
                   dictionary: str | None = None) -> MarkerMap:
    """A map of markers of one side ``length`` (m) from id -> (4, 4) ``T_map_marker``
    (e.g. ``MarkersScene.marker_poses``)."""
    markers = {int(i): MapMarker(int(i), float(length), np.asarray(T, dtype=np.float64)) for i, T in poses.items()}
    return MarkerMap(name, markers, dictionary)


def grid_map(name: str, columns: int, rows: int, length: float, separation: float, first_id: int = 0,
             dictionary: str | None = None) -> MarkerMap:
    """A ``columns`` x ``rows`` grid of markers (layout in the module docstring)."""
    pitch = length + separation
    poses = {}
    for n in range(columns * rows):
        row, column = divmod(n, columns)
        centre = np.array([column - (columns - 1) / 2, (rows - 1) / 2 - row, 0.0]) * pitch
        poses[first_id + n] = make_transform(np.eye(3), centre)
    return map_from_poses(name, poses, length, dictionary)


def load_marker_map(path: str | Path) -> MarkerMap:
    """The map described by the YAML file ``path``; MarkerMapError names the file, field and reason."""
    return parse_marker_map(read_yaml(path, MarkerMapError), str(path))


def save_marker_map(path: str | Path, marker_map: MarkerMap) -> None:
    """Write ``marker_map`` as a YAML file of the ``markers`` layout (each marker's id, length, position and
    quaternion), checked as ``parse_marker_map`` checks a file; ``load_marker_map`` reads it back."""
    document: dict[str, object] = {"name": marker_map.name}
    if marker_map.dictionary is not None:
        document["dictionary"] = marker_map.dictionary
    document["markers"] = [{"id": marker.id, "length": marker.length,
                            "position": marker.T_map_marker[:3, 3].tolist(),
                            "quaternion": quaternion_from_matrix(marker.T_map_marker[:3, :3]).tolist()}
                           for marker in marker_map.markers.values()]
    parse_marker_map(document, str(path))
    Path(path).write_text(yaml.safe_dump(document, sort_keys=False, default_flow_style=None))


def parse_marker_map(data: object, source: str = "marker map") -> MarkerMap:
    """The map described by ``data`` (the YAML layout, already parsed); errors name ``source``."""
    def fail(where: str, why: str) -> MarkerMapError:
        return MarkerMapError(f"{source}: {where}: {why}")

    if not isinstance(data, dict):
        raise fail("top level", f"must be a mapping with name and markers or grid, got {type(data).__name__}")
    unknown = sorted(set(data) - {"name", "dictionary", "markers", "grid"})
    if unknown:
        raise fail(", ".join(map(str, unknown)), "unknown field (valid: name, dictionary, markers, grid)")
    name = data.get("name")
    if not isinstance(name, str) or not NAME_PATTERN.fullmatch(name):
        raise fail("name", f"must be a word of letters, digits, '_', '.', '-', got {name!r}")
    dictionary = data.get("dictionary")
    size = None
    if dictionary is not None:
        if not isinstance(dictionary, str) or not dictionary.startswith("DICT_") or not hasattr(cv2.aruco, dictionary):
            raise fail("dictionary", f"must be a cv2.aruco dictionary name such as DICT_4X4_50, got {dictionary!r}")
        size = len(cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary)).bytesList)
    if ("markers" in data) == ("grid" in data):
        raise fail("markers/grid", "give exactly one of markers (a list) or grid (a mapping)")
    if "grid" in data:
        result = grid_map(name, dictionary=dictionary, **parse_grid(data["grid"], fail))
    else:
        result = MarkerMap(name, parse_markers(data["markers"], fail), dictionary)
    if size is not None and max(result.markers) >= size:
        raise fail("markers" if "markers" in data else "grid",
                   f"id {max(result.markers)} does not exist in {dictionary} (ids 0 to {size - 1})")
    return result


def parse_grid(grid: object, fail: Fail) -> dict:
    """Keyword arguments of ``grid_map`` from the ``grid`` mapping."""
    if not isinstance(grid, dict):
        raise fail("grid", f"must be a mapping with columns, rows, length, separation, first_id, got {grid!r}")
    unknown = sorted(set(grid) - {"columns", "rows", "length", "separation", "first_id"})
    if unknown:
        raise fail(f"grid.{unknown[0]}", "unknown field (valid: columns, rows, length, separation, first_id)")
    values: dict[str, float] = {"first_id": require_int(grid.get("first_id", 0), "grid.first_id", 0, fail)}
    for key in ("columns", "rows"):
        values[key] = require_int(grid.get(key), f"grid.{key}", 1, fail)
    if values["columns"] * values["rows"] > MAX_GRID_MARKERS:
        raise fail("grid", f"columns x rows must be at most {MAX_GRID_MARKERS} markers, "
                           f"got {values['columns']} x {values['rows']}")
    values["length"] = require_number(grid.get("length"), "grid.length", fail, positive=True)
    values["separation"] = require_number(grid.get("separation"), "grid.separation", fail)
    if values["separation"] < 0:
        raise fail("grid.separation", f"must be >= 0 (the gap between markers, metres), got {values['separation']}")
    return values


def parse_markers(markers: object, fail: Fail) -> dict[int, MapMarker]:
    """id -> MapMarker from the ``markers`` list."""
    if not isinstance(markers, list) or not markers:
        raise fail("markers", f"must be a non-empty list of {{id, length, position, quaternion}}, got {markers!r}")
    result: dict[int, MapMarker] = {}
    for n, entry in enumerate(markers):
        where = f"markers[{n}]"
        if not isinstance(entry, dict):
            raise fail(where, f"must be a mapping with id, length, position, quaternion, got {entry!r}")
        unknown = sorted(set(entry) - {"id", "length", "position", "quaternion"})
        if unknown:
            raise fail(f"{where}.{unknown[0]}", "unknown field (valid: id, length, position, quaternion)")
        marker_id = require_int(entry.get("id"), f"{where}.id", 0, fail)
        if marker_id in result:
            raise fail(f"{where}.id", f"id {marker_id} appears twice")
        length = require_number(entry.get("length"), f"{where}.length", fail, positive=True)
        position = require_vector(entry.get("position"), 3, f"{where}.position", fail)
        quaternion = require_vector(entry.get("quaternion", [0, 0, 0, 1]), 4, f"{where}.quaternion", fail)
        if abs(np.linalg.norm(quaternion) - 1) > 1e-3:
            raise fail(f"{where}.quaternion", f"must be a unit quaternion (x, y, z, w), norm is "
                                              f"{np.linalg.norm(quaternion):.6g}")
        result[marker_id] = MapMarker(marker_id, length, make_transform(matrix_from_quaternion(quaternion), position))
    return result


def require_int(value: object, where: str, low: int, fail: Fail) -> int:
    """``value`` as an int >= ``low``, or the error ``fail(where, why)``."""
    if isinstance(value, bool) or not isinstance(value, int) or value < low:
        raise fail(where, f"must be an integer >= {low}, got {value!r}")
    return value


def require_number(value: object, where: str, fail: Fail, positive: bool = False) -> float:
    """``value`` as a finite float (> 0 when ``positive``), or the error ``fail(where, why)``."""
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value) \
            or (positive and value <= 0):
        raise fail(where, f"must be a finite number{' > 0 (metres)' if positive else ''}, got {value!r}")
    return float(value)


def require_vector(value: object, size: int, where: str, fail: Fail) -> np.ndarray:
    """``value`` as a (size,) float64 array of finite numbers, or the error ``fail(where, why)``."""
    if not isinstance(value, list) or len(value) != size:
        raise fail(where, f"must be a list of {size} numbers, got {value!r}")
    return np.array([require_number(v, where, fail) for v in value])
