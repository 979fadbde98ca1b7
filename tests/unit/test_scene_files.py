"""Scenes written to files and read back: per-camera image folders, rig, bodies, target, marker map and truth
files."""

from pathlib import Path

import cv2
import numpy as np
import pytest

from services.calibration.camera_info import read_camera_info
from services.calibration.image_folder import seconds_to_ns
from services.calibration.rig import read_rig
from services.capture.sources import SourceError, SourceFrame, camera_names, frame_sizes, open_source
from services.estimation.bodies.file import load_bodies
from services.estimation.markers.map import load_marker_map
from services.estimation.targets.library import TargetLibrary
from services.launcher.scene_export import SceneExportError, export_scene, image_name
from services.recorder.trajectories import read_tum
from services.synthetic import make_scene
from services.synthetic.ir_rig import LAYOUTS

FRAMES = 4
SMALL = {"width": 160, "height": 120}


def frames_of(uri: str) -> list:
    source = open_source(uri)
    try:
        return list(source.frames())
    finally:
        source.close()


@pytest.fixture(scope="module")
def ir_folder(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("export") / "ir"
    export_scene("ir_rig", out, FRAMES, {"fps": 7.0, **SMALL})
    return out


def test_image_names_hold_the_time_to_the_nanosecond():
    for time_ns in (0, 142857143, 1_341_847_980_722_988_000, 999_999_999):
        name = image_name(time_ns)
        assert seconds_to_ns(Path(name).stem) == time_ns and name.endswith(".png")


def test_an_exported_ir_rig_reads_back_as_the_scene_it_came_from(ir_folder):
    scene = make_scene("ir_rig", fps=7.0, **SMALL)
    assert sorted(p.name for p in ir_folder.iterdir()) == ["bodies.yaml", "cam0", "cam0.yaml", "cam1", "cam1.yaml",
                                                          "rig.yaml", "scene.yaml", "truth"]
    rig = read_rig(ir_folder / "rig.yaml")
    for ours, theirs in zip(rig.cameras, scene.cameras, strict=True):
        assert ours.name == theirs.name and (ours.width, ours.height) == (theirs.width, theirs.height)
        np.testing.assert_allclose(ours.K, theirs.K, rtol=1e-12)
        np.testing.assert_allclose(ours.dist, theirs.dist, atol=1e-15)
        np.testing.assert_allclose(ours.T_rig_camera, theirs.T_rig_camera, atol=1e-12)
        assert np.allclose(read_camera_info(ir_folder / f"{ours.name}.yaml").K, theirs.K, rtol=1e-12)
    bodies = load_bodies(ir_folder / "bodies.yaml")
    assert list(bodies) == list(LAYOUTS)[:3] and all(np.array_equal(bodies[n], LAYOUTS[n]) for n in bodies)
    frames = frames_of(f"images:{ir_folder}")
    assert len(frames) == FRAMES and all(isinstance(f, SourceFrame) for f in frames)
    for index, frame in enumerate(frames):
        rendered = scene.render(index)
        assert frame.index == index and frame.time_ns == round(rendered.time_s * 1e9)
        assert list(frame.images) == ["cam0", "cam1"]
        assert all(np.array_equal(frame.images[c], rendered.images[c]) for c in frame.images)
    for name in bodies:
        truth = read_tum(ir_folder / "truth" / f"{name}.tum")
        assert truth.stamps_ns is not None and truth.stamps_ns.tolist() == [f.time_ns for f in frames]
        for index, T in enumerate(truth.poses):
            np.testing.assert_allclose(T, scene.body_poses(index)[name], atol=1e-12)


def test_the_capture_node_names_and_sizes_the_cameras_of_a_folder_of_folders(ir_folder):
    assert camera_names((f"images:{ir_folder}",), {}) == ["cam0", "cam1"]
    assert frame_sizes((f"images:{ir_folder}",), {}) == [(160, 120), (160, 120)]
    assert camera_names((f"images:{ir_folder / 'cam1'}",), {}) == ["cam0"]


def test_a_camera_scene_keeps_its_truth_per_camera_and_writes_no_rig(tmp_path):
    done = export_scene("markers", tmp_path / "m", 3, SMALL)
    assert done.fixtures.rig is None and done.fixtures.bodies is None and done.fixtures.targets is None
    assert (tmp_path / "m" / "cam0.yaml").is_file() and not (tmp_path / "m" / "rig.yaml").exists()
    scene = make_scene("markers", **SMALL)
    board = load_marker_map(tmp_path / "m" / "marker_map.yaml")
    assert done.fixtures.marker_map == tmp_path / "m" / "marker_map.yaml"
    assert board.name == "board" and board.dictionary == "DICT_4X4_50" and list(board.markers) == list(range(6))
    for marker_id, marker in board.markers.items():
        assert marker.length == scene.marker_length
        np.testing.assert_allclose(marker.T_map_marker, scene.marker_poses[marker_id], atol=1e-12)
    expected = {child.split("/")[-1] for i in range(3) for _, child, _ in scene.render(i).truth["cam0"]}
    assert expected and {p.stem for p in (tmp_path / "m" / "truth" / "cam0").iterdir()} == expected
    assert [f.index for f in frames_of(f"images:{tmp_path / 'm'}")] == [0, 1, 2]


def test_a_target_scene_writes_its_target_as_a_library(tmp_path):
    done = export_scene("planar_target", tmp_path / "t", 1, {"texture_px": 256, **SMALL})
    scene = make_scene("planar_target", texture_px=256, **SMALL)
    assert done.fixtures.targets == tmp_path / "t" / "targets" and done.fixtures.marker_map is None
    library = TargetLibrary(done.fixtures.targets)
    assert library.names() == ["planar_target"]
    target = library.load("planar_target")
    assert np.array_equal(target.image, scene.texture) and target.width_m == scene.size_m[0]


def test_a_wand_scene_says_why_it_has_no_bodies_file(tmp_path):
    done = export_scene("ir_rig", tmp_path / "w", 1, {"motion": "wand", **SMALL})
    notes = done.fixtures.notes
    assert done.fixtures.bodies is None and len(notes) == 1 and "one line" in notes[0]
    assert (tmp_path / "w" / "truth" / "calibration_wand.tum").is_file()


def test_bad_exports_are_refused(tmp_path):
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "x").write_text("")
    with pytest.raises(SceneExportError, match="not an empty folder"):
        export_scene("ir_rig", tmp_path / "full", 1)
    with pytest.raises(SceneExportError, match="--frames"):
        export_scene("ir_rig", tmp_path / "a", 0)
    with pytest.raises(SceneExportError, match="unknown scene"):
        export_scene("nothing", tmp_path / "b", 1)


def write_images(folder: Path, names: list[str], value: int = 0) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for name in names:
        cv2.imwrite(str(folder / name), np.full((8, 8), value, np.uint8))


def test_untimed_folders_pair_by_file_name(tmp_path):
    write_images(tmp_path / "left", ["b.png", "a.png"], 1)
    write_images(tmp_path / "right", ["a.png", "b.png"], 2)
    frames = frames_of(f"images:{tmp_path}")
    assert [f.time_ns for f in frames] == [None, None] and [list(f.images) for f in frames] == [["left", "right"]] * 2
    assert frames[0].images["right"][0, 0] == 2


@pytest.mark.parametrize(("left", "right", "message"), [
    (["0.1.png", "0.2.png"], ["0.1.png", "0.3.png"], "left/0.2.png has no partner in right/"),
    (["0.1.png"], ["0.1.png", "0.2.png"], "right/0.2.png has no partner in left/"),
    (["0.1.png"], ["a.png"], "left have frame times, right not"),
])
def test_folders_that_do_not_pair_are_refused_in_one_line(tmp_path, left, right, message):
    write_images(tmp_path / "left", left)
    write_images(tmp_path / "right", right)
    with pytest.raises(SourceError) as caught:
        open_source(f"images:{tmp_path}")
    assert message in str(caught.value) and "\n" not in str(caught.value)


def test_cameras_are_in_natural_order(tmp_path):
    for name in ("cam10", "cam2", "cam1"):
        write_images(tmp_path / name, ["0.5.png"])
    (tmp_path / "truth").mkdir()
    assert camera_names((f"images:{tmp_path}",), {}) == ["cam1", "cam2", "cam10"]


def test_a_kitti_sequence_is_a_rig_timed_by_its_times_file(tmp_path):
    write_images(tmp_path / "image_0", ["000000.png", "000001.png"])
    write_images(tmp_path / "image_1", ["000000.png", "000001.png"])
    (tmp_path / "times.txt").write_text("0.000000e+00\n1.036000e-01\n")
    frames = frames_of(f"images:{tmp_path}")
    assert [(f.time_ns, list(f.images)) for f in frames] == [(0, ["image_0", "image_1"]),
                                                            (103_600_000, ["image_0", "image_1"])]
