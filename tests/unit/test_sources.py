"""Frame sources: video files, image folders (plain, TUM, KITTI), scenes, and their errors."""

from pathlib import Path

import cv2
import numpy as np
import pytest

from services.calibration.camera_info import CalibrationError, read_camera_info, write_camera_info
from services.calibration.image_folder import seconds_to_ns
from services.capture.sources import FrameFault, SourceError, SourceFrame, check_source, check_uri, open_source
from services.geometry.camera import CameraModel, project_points
from services.geometry.se3 import invert, transform_points
from tests.data import data_dir


def frames_of(uri: str, **kwargs) -> list:
    source = open_source(uri, **kwargs)
    try:
        return list(source.frames())
    finally:
        source.close()


def gradient(i: int, shape=(48, 64)) -> np.ndarray:
    return ((np.arange(shape[0] * shape[1]).reshape(shape) + 7 * i) % 251).astype(np.uint8)


def test_image_folder_in_name_order_without_times(tmp_path):
    for i in (2, 0, 1):
        cv2.imwrite(str(tmp_path / f"frame{i:03d}.png"), gradient(i))
    frames = frames_of(f"images:{tmp_path}")
    assert [f.index for f in frames] == [0, 1, 2] and all(f.time_s is None for f in frames)
    for i, frame in enumerate(frames):
        assert np.array_equal(frame.images["cam0"], gradient(i))


def test_tum_names_and_rgb_list_give_times(tmp_path):
    for stamp in ("1341847981.5", "1341847980.25"):
        cv2.imwrite(str(tmp_path / f"{stamp}.png"), gradient(0))
    assert [f.time_s for f in frames_of(f"images:{tmp_path}")] == [1341847980.25, 1341847981.5]
    (tmp_path / "rgb.txt").write_text("# timestamp filename\n1341847981.5 1341847981.5.png\n")
    assert [f.time_s for f in frames_of(f"images:{tmp_path}")] == [1341847981.5]


def test_tum_names_and_rgb_list_give_exact_nanoseconds(tmp_path):
    cv2.imwrite(str(tmp_path / "1341847980.722988.png"), gradient(0))
    cv2.imwrite(str(tmp_path / "1341847980.790991.png"), gradient(1))
    assert [f.time_ns for f in frames_of(f"images:{tmp_path}")] == [1341847980722988000, 1341847980790991000]
    (tmp_path / "rgb.txt").write_text("# timestamp filename\n1341847980.790991 1341847980.790991.png\n")
    assert [f.time_ns for f in frames_of(f"images:{tmp_path}")] == [1341847980790991000]


def test_kitti_times_in_scientific_notation_give_exact_nanoseconds(tmp_path):
    for i in range(2):
        cv2.imwrite(str(tmp_path / f"{i:06d}.png"), gradient(i))
    (tmp_path / "times.txt").write_text("1.036150e-01\n4.662529e+03\n")
    assert [f.time_ns for f in frames_of(f"images:{tmp_path}")] == [103615000, 4662529000000]


@pytest.mark.parametrize("text", ["1341847980.722988", "0.000000001", "1.036150e-01", "4662.5290005", "7",
                                  "1305031102.175304", "0.0000000005", "0.0000000015"])
def test_seconds_to_ns_agrees_with_exact_fractions(text):
    from fractions import Fraction

    assert seconds_to_ns(text) == round(Fraction(text) * 1_000_000_000)  # round(): half to even, as seconds_to_ns


def test_a_time_list_entry_that_is_not_a_number_is_refused_naming_the_list(tmp_path):
    cv2.imwrite(str(tmp_path / "a.png"), gradient(0))
    (tmp_path / "rgb.txt").write_text("# timestamp filename\nnoon a.png\n")
    with pytest.raises(SourceError, match=r"rgb.txt: entry 2: 'noon' is not a time in seconds"):
        open_source(f"images:{tmp_path}")


def test_kitti_times_in_parent_folder(tmp_path):
    images = tmp_path / "image_0"
    images.mkdir()
    for i in range(3):
        cv2.imwrite(str(images / f"{i:06d}.png"), gradient(i))
    (tmp_path / "times.txt").write_text("0.0\n0.103\n0.206\n")
    assert [f.time_s for f in frames_of(f"images:{images}")] == [0.0, 0.103, 0.206]


def test_unreadable_image_mid_folder_is_a_fault_and_the_rest_flows(tmp_path):
    cv2.imwrite(str(tmp_path / "a.png"), gradient(0))
    (tmp_path / "b.png").write_bytes(b"not a png at all")
    cv2.imwrite(str(tmp_path / "c.png"), gradient(2))
    frames = frames_of(f"images:{tmp_path}")
    assert isinstance(frames[1], FrameFault) and "b.png" in frames[1].reason
    assert [type(f) for f in frames] == [SourceFrame, FrameFault, SourceFrame]


def test_video_file_frames_and_times(tmp_path):
    path = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (64, 48))
    for i in range(5):
        writer.write(cv2.cvtColor(gradient(20 * i), cv2.COLOR_GRAY2BGR))
    writer.release()
    frames = frames_of(f"video:{path}")
    assert len(frames) == 5
    assert [round(f.time_s, 3) for f in frames] == [0.0, 0.1, 0.2, 0.3, 0.4]
    grey = cv2.cvtColor(frames[3].images["cam0"], cv2.COLOR_BGR2GRAY)
    assert np.abs(grey.astype(int) - gradient(60)).mean() < 6  # MJPG is lossy


def test_synthetic_scene_frames_carry_truth_and_calibration():
    source = open_source("synthetic:markers", frames=3, scene_options={"seed": 1})
    frames = list(source.frames())
    assert len(frames) == 3 and source.camera_names == ("cam0",)
    assert "cam0" in source.calibration and frames[0].truth["cam0"]


def test_a_prerendered_scene_sends_its_first_instants_over_and_over_timed_as_it_goes():
    options = {"seed": 2, "fps": 120.0}
    rendered = list(open_source("synthetic:ir_rig", frames=3, scene_options=options).frames())
    cycled = list(open_source("synthetic:ir_rig", frames=7, scene_options=options, prerender=3).frames())
    assert [f.index for f in cycled] == list(range(7))
    for frame in cycled:
        again = rendered[frame.index % 3]
        assert all(np.array_equal(frame.images[c], again.images[c]) for c in again.images)
        assert frame.truth.keys() == again.truth.keys()
        for camera, poses in frame.truth.items():
            assert [(parent, child) for parent, child, _ in poses] == [(p, c) for p, c, _ in again.truth[camera]]
            assert all(np.array_equal(a[2], b[2]) for a, b in zip(poses, again.truth[camera], strict=True))
    assert [f.time_ns for f in cycled] == [round(i * 1e9 / 120) for i in range(7)]


@pytest.mark.parametrize(("uri", "expected"), [
    ("camera:97", "cannot open video device 97"),
    ("video:/no/such/clip.mp4", "no such file"),
    ("video:/tmp", "a folder, not a video file \\(a folder of images is images:/tmp\\)"),
    ("images:/no/such/folder", "no such folder"),
    ("synthetic:teapot", "unknown scene 'teapot'"),
    ("webcam:0", "is not a source URI"),
    ("camera:front", "device number"),
])
def test_sources_that_cannot_start_name_the_reason(uri, expected):
    with pytest.raises(SourceError, match=expected) as caught:
        open_source(uri)
    assert uri.split(":")[0] in str(caught.value)


def test_empty_folder_and_unreadable_video_are_refused(tmp_path):
    with pytest.raises(SourceError, match="no image files"):
        open_source(f"images:{tmp_path}")
    bad = tmp_path / "clip.mp4"
    bad.write_text("not a video")
    with pytest.raises(SourceError, match="OpenCV cannot read this file"):
        open_source(f"video:{bad}")
    with pytest.raises(SourceError, match="OpenCV cannot read this file"):
        check_source(f"video:{bad}")  # before the job starts


def test_check_uri_splits_scheme():
    assert check_uri("video:/a/b:c.mp4") == ("video", "/a/b:c.mp4")


def test_camera_info_yaml_round_trip(tmp_path):
    camera = CameraModel("left", 640, 480, np.array([[500.0, 0, 320.5], [0, 501.0, 240.25], [0, 0, 1]]),
                         np.array([0.1, -0.2, 0.001, 0.002, 0.05]), np.eye(4))
    path = tmp_path / "left.yaml"
    write_camera_info(path, camera)
    back = read_camera_info(path)
    assert (back.name, back.width, back.height) == ("left", 640, 480)
    assert np.array_equal(back.K, camera.K) and np.array_equal(back.dist, camera.dist)
    assert "camera_matrix:" in path.read_text() and "distortion_model: plumb_bob" in path.read_text()


@pytest.mark.parametrize(("text", "expected"), [
    ("image_width: 640\nimage_height: 480\n", "missing camera_matrix"),
    ("image_width: 0\n", "image_width must be a positive integer"),
    ("image_width: 640\nimage_height: 480\ncamera_matrix: {rows: 3, cols: 3, data: [1, 2]}\n", "needs 9 numbers"),
    ("image_width: 640\nimage_height: 480\ndistortion_model: equidistant\n", "plumb_bob only"),
    ("image_width: 640\nimage_height: 480\n"
     "camera_matrix: {rows: 3, cols: 3, data: [.nan, 0, 320, 0, 500, 240, 0, 0, 1]}\n",
     "camera_matrix.data holds a value that is not finite"),
    ("[unclosed", "not valid YAML"),
])
def test_bad_camera_info_names_the_field(tmp_path: Path, text: str, expected: str):
    path = tmp_path / "cam.yaml"
    path.write_text(text)
    with pytest.raises(CalibrationError, match=expected):
        read_camera_info(path)


KITTI_P = (np.array([[707.0912, 0, 601.8873, 0], [0, 707.0912, 183.1104, 0], [0, 0, 1, 0]]),
           np.array([[707.0912, 0, 601.8873, -379.8145], [0, 707.0912, 183.1104, 0], [0, 0, 1, 0]]))
"""KITTI odometry sequence 06's P0 and P1 (left and right grey cameras, 0.537 m apart)."""


def kitti_sequence(root: Path, named: bool = True, frames: int = 2) -> Path:
    for i in range(len(KITTI_P)):
        (root / f"image_{i}").mkdir(parents=True)
        for j in range(frames):
            cv2.imwrite(str(root / f"image_{i}" / f"{j:06d}.png"), gradient(j, (37, 122)))
    lines = [(f"P{i}: " if named else "") + " ".join(f"{v:.12e}" for v in P.ravel()) for i, P in enumerate(KITTI_P)]
    (root / "calib.txt").write_text("\n".join([*lines, "Tr: " + " ".join(["0"] * 12)] if named else lines) + "\n")
    return root


@pytest.mark.parametrize("named", [True, False])
def test_a_kitti_folder_is_calibrated_by_the_calib_file_beside_it(tmp_path, named):
    root = kitti_sequence(tmp_path, named)
    alone = open_source(f"images:{root / 'image_0'}").calibration
    assert list(alone) == ["cam0"] and np.allclose(alone["cam0"].K, KITTI_P[0][:, :3])
    assert (alone["cam0"].width, alone["cam0"].height) == (122, 37) and not alone["cam0"].dist.any()
    rig = open_source(f"images:{root}").calibration
    assert sorted(rig) == ["image_0", "image_1"] and np.allclose(rig["image_1"].K, KITTI_P[1][:, :3])
    assert np.allclose(rig["image_0"].T_rig_camera, np.eye(4))
    assert np.allclose(rig["image_1"].T_rig_camera[:3, 3], [379.8145 / 707.0912, 0, 0])  # the baseline, 0.537 m
    points = np.random.default_rng(6).uniform([-5, -2, 4], [5, 2, 40], (20, 3))  # in camera 0's frame
    for name, P in zip(("image_0", "image_1"), KITTI_P, strict=True):
        camera = rig[name]
        in_camera = transform_points(invert(camera.T_rig_camera), points)
        projected = (P @ np.c_[points, np.ones(len(points))].T).T
        assert np.allclose(project_points(in_camera, camera.K), projected[:, :2] / projected[:, 2:], atol=1e-6)


def test_a_damaged_kitti_calib_line_is_refused_naming_the_file_and_line(tmp_path):
    root = kitti_sequence(tmp_path)
    (root / "calib.txt").write_text("P0: 1 2 3\n")
    with pytest.raises(CalibrationError, match=r"calib.txt:1: P0 needs 12 finite numbers"):
        _ = open_source(f"images:{root / 'image_0'}").calibration


def test_a_folder_not_named_as_kittis_is_not_calibrated_by_a_calib_file(tmp_path):
    root = kitti_sequence(tmp_path)
    (root / "image_0").rename(root / "left")
    assert open_source(f"images:{root / 'left'}").calibration == {}


def test_the_real_kitti_sequence_gives_its_frames_and_p0_calibration():
    folder = data_dir("vo_kitti_odometry_seq06_frames000-050") / "image_0"
    source = open_source(f"images:{folder}")
    camera = source.calibration["cam0"]
    assert np.allclose(camera.K, [[707.0912, 0, 601.8873], [0, 707.0912, 183.1104], [0, 0, 1]])
    assert (camera.width, camera.height) == (1226, 370)
    frames = list(source.frames())
    assert len(frames) == 51 and all(f.images["cam0"].shape == (370, 1226) for f in frames)
    assert all(f.time_ns is None for f in frames)  # no times.txt in this copy: paced by --fps, or 30 fps


def test_the_real_tum_folder_gives_its_frames_stamped_by_their_names():
    folder = data_dir("tum_rgbd_fr3_long_office_household_1hz") / "rgb"
    frames = list(open_source(f"images:{folder}").frames())
    stamps = [f.time_ns for f in frames]
    assert len(frames) == 20 and stamps == sorted(stamps) and stamps[0] == 1_341_847_980_722_988_000
    assert all(f.images["cam0"].shape == (480, 640, 3) for f in frames)
    assert open_source(f"images:{folder}").calibration == {}  # TUM ships no calibration file: give --calib
