"""Marker maps: YAML files (explicit markers or a grid), the grid layout against the synthetic
markers scene, and one clear error per bad file."""

import numpy as np
import pytest

from services.estimation.markers.map import (
    MarkerMapError,
    grid_map,
    load_marker_map,
    map_from_poses,
    marker_corners,
    parse_marker_map,
    save_marker_map,
)
from services.geometry.rotation import matrix_from_quaternion, matrix_from_rotvec
from services.geometry.se3 import make_transform
from services.synthetic import make_scene

DEFAULT_SCENE_GRID = """\
name: board
dictionary: DICT_4X4_50
grid: {columns: 3, rows: 2, length: 0.05, separation: 0.05, first_id: 0}
"""


def write(tmp_path, text: str):
    path = tmp_path / "map.yaml"
    path.write_text(text)
    return path


def test_the_grid_file_is_the_default_markers_scene(tmp_path):
    scene = make_scene("markers")
    loaded = load_marker_map(write(tmp_path, DEFAULT_SCENE_GRID))
    expected = map_from_poses("board", scene.marker_poses, scene.marker_length)
    assert loaded.name == "board" and loaded.dictionary == "DICT_4X4_50"
    assert sorted(loaded.markers) == sorted(expected.markers) == [0, 1, 2, 3, 4, 5]
    for marker_id, marker in loaded.markers.items():
        assert marker.length == 0.05
        assert np.allclose(marker.T_map_marker, expected.markers[marker_id].T_map_marker, atol=1e-12)
        assert np.allclose(marker.corners(), scene.marker_corners[marker_id], atol=1e-12)


def test_a_saved_map_reads_back_as_it_was(tmp_path):
    poses = {7: make_transform(matrix_from_rotvec(np.array([0.3, -1.2, 2.9])), np.array([0.1, -0.2, 0.05])),
             2: np.eye(4)}
    saved = map_from_poses("table", poses, 0.08, "DICT_5X5_100")
    save_marker_map(tmp_path / "table.yaml", saved)
    loaded = load_marker_map(tmp_path / "table.yaml")
    assert (loaded.name, loaded.dictionary, list(loaded.markers)) == ("table", "DICT_5X5_100", [7, 2])
    for marker_id, marker in loaded.markers.items():
        assert marker.length == 0.08
        np.testing.assert_allclose(marker.T_map_marker, poses[marker_id], atol=1e-12)
    with pytest.raises(MarkerMapError, match="id 60 does not exist in DICT_4X4_50"):
        save_marker_map(tmp_path / "bad.yaml", map_from_poses("bad", {60: np.eye(4)}, 0.05, "DICT_4X4_50"))


def test_grid_layout_runs_row_by_row_from_the_top_left():
    board = grid_map("b", columns=2, rows=3, length=0.1, separation=0.02, first_id=10)
    centres = {i: m.T_map_marker[:3, 3] for i, m in board.markers.items()}
    assert sorted(centres) == list(range(10, 16))
    assert np.allclose(centres[10], [-0.06, 0.12, 0.0]) and np.allclose(centres[11], [0.06, 0.12, 0.0])
    assert np.allclose(centres[15], [0.06, -0.12, 0.0])
    assert np.allclose(sum(centres.values()), 0.0)


def test_explicit_markers_with_position_and_quaternion(tmp_path):
    text = """\
name: table
markers:
  - {id: 3, length: 0.05, position: [0.1, 0.2, 0.0]}
  - {id: 7, length: 0.08, position: [0.0, 0.0, 0.3], quaternion: [0.0, 0.7071068, 0.0, 0.7071068]}
"""
    table = load_marker_map(write(tmp_path, text))
    assert table.name == "table" and table.dictionary is None
    assert np.allclose(table.markers[3].T_map_marker, [[1, 0, 0, 0.1], [0, 1, 0, 0.2], [0, 0, 1, 0], [0, 0, 0, 1]])
    seven = table.markers[7]
    assert seven.length == 0.08
    assert np.allclose(seven.T_map_marker[:3, :3], matrix_from_quaternion([0, 1, 0, 1]))
    assert np.allclose(seven.corners()[0], seven.T_map_marker[:3, :3] @ [-0.04, 0.04, 0.0] + [0, 0, 0.3])


def test_marker_corners_are_in_aruco_order():
    assert np.allclose(marker_corners(0.1), [[-0.05, 0.05, 0], [0.05, 0.05, 0], [0.05, -0.05, 0], [-0.05, -0.05, 0]])


@pytest.mark.parametrize(("text", "field", "why"), [
    ("grid: {columns: 1, rows: 1, length: 0.05, separation: 0}", "name", "must be a word"),
    ("name: a/b\ngrid: {columns: 1, rows: 1, length: 0.05, separation: 0}", "name", "must be a word"),
    ("name: b", "markers/grid", "exactly one"),
    ("name: b\nmarkers: []\ngrid: {}", "markers/grid", "exactly one"),
    ("name: b\ncolour: red\nmarkers: []", "colour", "unknown field"),
    ("name: b\ndictionary: DICT_9X9\ngrid: {columns: 1, rows: 1, length: 1, separation: 0}", "dictionary",
     "DICT_4X4_50"),
    ("name: b\ngrid: {columns: 0, rows: 1, length: 0.05, separation: 0}", "grid.columns", "integer >= 1"),
    ("name: b\ngrid: {columns: 1, rows: 1, length: -1, separation: 0}", "grid.length", "> 0"),
    ("name: b\ngrid: {columns: 1, rows: 1, length: 1, separation: -0.1}", "grid.separation", ">= 0"),
    ("name: b\ngrid: {colums: 1, rows: 1, length: 1, separation: 0}", "grid.colums", "unknown field"),
    ("name: b\ngrid: [1, 2]", "grid", "must be a mapping"),
    ("name: b\ngrid: {columns: 100000, rows: 100000, length: 1, separation: 0}", "grid", "at most 1000"),
    ("name: b\nmarkers: []", "markers", "non-empty list"),
    ("name: b\nmarkers: [{id: 1, length: 0.05}]", "markers[0].position", "list of 3 numbers"),
    ("name: b\nmarkers: [{id: 1, length: 0, position: [0, 0, 0]}]", "markers[0].length", "> 0"),
    ("name: b\nmarkers: [{id: -1, length: 1, position: [0, 0, 0]}]", "markers[0].id", "integer >= 0"),
    ("name: b\nmarkers: [{id: 1, length: 1, position: [0, 0, .nan]}]", "markers[0].position", "finite"),
    ("name: b\nmarkers: [{id: 1, length: 1, position: [0, 0, 0], quaternion: [0, 0, 0, 2]}]",
     "markers[0].quaternion", "unit quaternion"),
    ("name: b\nmarkers: [{id: 1, length: 1, position: [0, 0, 0]}, {id: 1, length: 1, position: [1, 0, 0]}]",
     "markers[1].id", "appears twice"),
    ("name: b\nmarkers: [{id: 1, length: 1, position: [0, 0, 0], size: 2}]", "markers[0].size", "unknown field"),
    ("name: b\ndictionary: DICT_4X4_50\nmarkers: [{id: 50, length: 1, position: [0, 0, 0]}]", "markers",
     "does not exist in DICT_4X4_50"),
    ("name: b\ndictionary: DICT_4X4_50\ngrid: {columns: 8, rows: 8, length: 1, separation: 0}", "grid",
     "id 63 does not exist"),
    ("- just\n- a list", "top level", "must be a mapping"),
])
def test_a_bad_file_names_the_file_the_field_and_why(tmp_path, text, field, why):
    path = write(tmp_path, text)
    with pytest.raises(MarkerMapError) as raised:
        load_marker_map(path)
    message = str(raised.value)
    assert message.startswith(f"{path}: {field}: ") and why in message


def test_unreadable_and_invalid_yaml_files_are_marker_map_errors(tmp_path):
    with pytest.raises(MarkerMapError, match="cannot read"):
        load_marker_map(tmp_path / "missing.yaml")
    with pytest.raises(MarkerMapError, match="not valid YAML"):
        load_marker_map(write(tmp_path, "name: [unclosed"))
    assert issubclass(MarkerMapError, ValueError)


def test_parse_names_its_source():
    with pytest.raises(MarkerMapError, match="^settings: name: "):
        parse_marker_map({"name": ""}, "settings")
