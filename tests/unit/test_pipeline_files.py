"""The pipeline files and board shipped in ``pipelines/`` are valid and describe what they say."""

import shlex
from pathlib import Path

import numpy as np

from services.cli import main
from services.estimation.markers.map import load_marker_map
from services.launcher.pipeline import read_pipeline
from services.synthetic import make_scene

PIPELINES = Path(__file__).resolve().parents[2] / "pipelines"


WIRING = {
    "echo.toml": {"cam": (), "echo": ("cam",)},
    "marker.toml": {"capture": (), "marker-cam0": ("capture",)},
    "marker_board.toml": {"cam": (), "markers": ("cam",), "pose": ("cam", "markers")},
}
"""Each bundled pipeline file: the nodes each of its nodes reads from (its flow plan's upstream)."""


def test_every_bundled_pipeline_file_wires_its_nodes_to_one_another():
    wiring = {path.name: {name: plan.upstream for name, plan in read_pipeline(path).flow_plans().items()}
              for path in sorted(PIPELINES.glob("*.toml"))}
    assert wiring == WIRING


def test_the_bundled_board_is_the_markers_scene_board():
    board = load_marker_map(PIPELINES / "board.yaml")
    scene = make_scene("markers")
    assert set(board.markers) == set(scene.marker_poses)
    for marker_id, marker in board.markers.items():
        assert marker.length == scene.marker_length
        assert np.allclose(marker.T_map_marker, scene.marker_poses[marker_id])


def test_the_marker_pipeline_file_is_what_artrack_run_marker_saves(tmp_path):
    """`artrack run marker ...` and `artrack up pipelines/marker.toml` run the same pipeline: the file is
    the saved form of the one-liner written in its first line."""
    first = (PIPELINES / "marker.toml").read_text().splitlines()[0]
    assert first.startswith("# Written by: artrack run marker ")
    saved = tmp_path / "saved.toml"
    argv = [*shlex.split(first.removeprefix("# Written by: "))[1:], "--save-pipeline", str(saved)]
    assert main(argv) == 0
    assert read_pipeline(saved).nodes == read_pipeline(PIPELINES / "marker.toml").nodes
    assert saved.read_text().split("\n\n", 1)[1] in (PIPELINES / "marker.toml").read_text()


def test_a_pipeline_file_that_exists_is_kept_unless_forced(tmp_path, capsys):
    saved = tmp_path / "job.toml"
    saved.write_text("kept")
    argv = ["run", "marker", "--source", "synthetic:markers", "--marker-length", "0.05", "--save-pipeline", str(saved)]
    assert main(argv) == 2
    assert f"{saved} exists: give --force to overwrite it" in capsys.readouterr().err
    assert saved.read_text() == "kept"
    assert main([*argv, "--force"]) == 0
    assert "marker-cam0" in read_pipeline(saved).nodes
