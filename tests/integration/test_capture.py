"""The capture node as a real process: files and scenes in, frames on their keys out."""

import cv2
import numpy as np
import pytest

from protocol import CameraInfo, GroundTruth, Image
from services.bus.pubsub import Inbox, Role
from services.calibration.camera_info import write_camera_info
from services.geometry.camera import CameraModel
from tests.integration.support import START_S, collect, start_node, wait_live

pytestmark = pytest.mark.integration


def test_image_folder_with_calibration_flows_in_order(bus, procs, session, tmp_path):
    folder = tmp_path / "frames"
    folder.mkdir()
    pictures = [np.full((48, 64, 3), (10 * i, 100, 200 - i), np.uint8) for i in range(6)]
    for i, picture in enumerate(pictures):
        cv2.imwrite(str(folder / f"{i:04d}.png"), picture)
    K = np.array([[70.0, 0, 31.5], [0, 70.0, 23.5], [0, 0, 1]])
    write_camera_info(tmp_path / "left.yaml", CameraModel("left", 64, 48, K, np.zeros(5), np.eye(4)))
    keys = bus.keys
    images = Inbox(session, keys.image("left"), Image, Role.RESULT)
    infos = Inbox(session, keys.camera_info("left"), CameraInfo, Role.RESULT)
    try:
        cam = start_node(procs, "capture", "cam", source=f"images:{folder}", cameras=["left"], fps=50,
                         calib=[str(tmp_path / "left.yaml")], wait_for_subscriber=True)
        got = collect(images, 6)
        assert cam.wait(START_S) == 0, cam.describe()  # a finite source ends the node cleanly
        assert [m.header.seq for m in got] == list(range(6))
        assert all(m.encoding == "bgr8" and np.array_equal(m.data, p) for m, p in zip(got, pictures, strict=True))
        info = collect(infos, 6)[-1]
        assert np.array_equal(np.array(info.k).reshape(3, 3), K) and info.header == got[-1].header
    finally:
        images.close()
        infos.close()


def test_two_camera_scene_shares_stamps_and_publishes_truth(bus, procs, session):
    keys = bus.keys
    inboxes = {name: Inbox(session, keys.image(name), Image, Role.RESULT) for name in ("cam0", "cam1")}
    truth = Inbox(session, keys.truth("cam1"), GroundTruth, Role.RESULT)
    try:
        start_node(procs, "capture", "rig", source="synthetic:ir_rig", frames=4, fps=20, wait_for_subscriber=True,
                   flow={"lossless": True})  # frames block rather than drop on a busy bus: all four arrive
        left, right = collect(inboxes["cam0"], 4), collect(inboxes["cam1"], 4)
        assert [m.header for m in left] == [m.header.model_copy(update={"frame_id": "cam0"}) for m in right]
        assert [m.header.frame_id for m in right] == ["cam1"] * 4
        bodies = {t.child_frame for t in collect(truth, 4)[0].transforms}
        assert len(bodies) >= 2 and all(b.startswith("body/") for b in bodies)
    finally:
        for inbox in [*inboxes.values(), truth]:
            inbox.close()


def test_missing_camera_exits_with_one_clear_line(procs):
    cam = start_node(procs, "capture", "cam", source="camera:97")
    assert cam.wait(START_S) == 2, cam.describe()
    errors = [line for line in cam.stderr.splitlines() if "ERROR" in line]
    assert len(errors) == 1 and "camera:97" in errors[0] and "cannot open video device 97" in errors[0]
    assert "WARN" not in cam.stderr and "cap_v4l" not in cam.stderr, cam.stderr  # OpenCV's own log kept quiet


def test_a_looped_folder_starts_over_and_keeps_counting(bus, procs, session, tmp_path):
    pictures = [np.full((32, 32), 40 * (i + 1), np.uint8) for i in range(3)]
    for i, picture in enumerate(pictures):
        cv2.imwrite(str(tmp_path / f"{i}.png"), picture)
    images = Inbox(session, bus.keys.image("cam0"), Image, Role.RESULT)
    try:
        cam = start_node(procs, "capture", "cam", source=f"images:{tmp_path}", loop=True, frames=7, fps=40,
                         wait_for_subscriber=True)
        got = collect(images, 7)
        assert cam.wait(START_S) == 0, cam.describe()
        assert [m.header.seq for m in got] == list(range(7))
        assert [int(m.data[0, 0]) for m in got] == [40, 80, 120, 40, 80, 120, 40]
    finally:
        images.close()


def _folder_and_calibration(tmp_path, frame_size: tuple[int, int], calibrated: tuple[int, int]):
    folder = tmp_path / "frames"
    folder.mkdir()
    for i in range(3):
        cv2.imwrite(str(folder / f"{i:04d}.png"), np.full((frame_size[1], frame_size[0]), 40 * i, np.uint8))
    width, height = calibrated
    K = np.array([[0.8 * width, 0, width / 2 - 0.5], [0, 0.8 * width, height / 2 - 0.5], [0, 0, 1]])
    calib = tmp_path / "hd.yaml"
    write_camera_info(calib, CameraModel("cam0", width, height, K, np.array([0.1, -0.2, 0, 0, 0.05]), np.eye(4)))
    return folder, calib, K


def test_a_calibration_of_another_aspect_ratio_stops_the_capture_naming_both_sizes(procs, tmp_path):
    folder, calib, _ = _folder_and_calibration(tmp_path, (64, 48), (128, 72))
    cam = start_node(procs, "capture", "cam", source=f"images:{folder}", calib=[str(calib)], fps=50)
    assert cam.wait(START_S) == 2, cam.describe()
    errors = [line for line in cam.stderr.splitlines() if "ERROR" in line]
    assert len(errors) == 1 and f"{calib}: calibrated for 128x72, the frames are 64x48" in errors[0], cam.stderr


def test_a_calibration_of_the_same_aspect_ratio_is_scaled_to_the_frames_with_one_warning(bus, procs, session,
                                                                                           tmp_path):
    folder, calib, K = _folder_and_calibration(tmp_path, (64, 36), (128, 72))
    infos = Inbox(session, bus.keys.camera_info("cam0"), CameraInfo, Role.RESULT)
    images = Inbox(session, bus.keys.image("cam0"), Image, Role.RESULT)  # what the capture waits for
    try:
        cam = start_node(procs, "capture", "cam", source=f"images:{folder}", calib=[str(calib)], fps=50,
                         wait_for_subscriber=True)
        got = collect(infos, 3)
        assert cam.wait(START_S) == 0, cam.describe()
        scaled = np.array([[0.5 * K[0, 0], 0, (K[0, 2] + 0.5) / 2 - 0.5], [0, 0.5 * K[1, 1], (K[1, 2] + 0.5) / 2 - 0.5],
                           [0, 0, 1]])
        for info in got:
            assert (info.width, info.height) == (64, 36)
            np.testing.assert_allclose(np.array(info.k).reshape(3, 3), scaled, rtol=0, atol=1e-12)
            np.testing.assert_array_equal(info.d, [0.1, -0.2, 0, 0, 0.05])
        warnings = [line for line in cam.stderr.splitlines() if "intrinsics scaled by 0.5" in line]
        assert len(warnings) == 1 and "calibrated for 128x72, the frames are 64x36" in warnings[0], cam.stderr
    finally:
        infos.close()
        images.close()


def test_run_refuses_a_calibration_of_another_aspect_ratio_before_starting(procs, tmp_path):
    folder, calib, _ = _folder_and_calibration(tmp_path, (64, 48), (128, 72))
    job = procs.run("run", "echo", "--source", f"images:{folder}", "--calib", str(calib))
    assert job.poll() == 2, job.describe()
    lines = [line for line in job.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and f"nodes.capture: {calib}: calibrated for 128x72, the frames are 64x48" in lines[0]


def test_a_marker_node_refuses_a_calibration_file_of_another_aspect_ratio(bus, procs, session, tmp_path):
    folder, calib, _ = _folder_and_calibration(tmp_path, (64, 48), (128, 72))
    marker = start_node(procs, "marker_pose", "marker", calib=str(calib), marker_length=0.05)
    wait_live(session, bus.keys, {"marker"}, [marker])
    start_node(procs, "capture", "cam", source=f"images:{folder}", fps=20, loop=True)
    assert marker.wait(START_S) == 2, marker.describe()
    errors = [line for line in marker.stderr.splitlines() if "ERROR" in line]
    assert len(errors) == 1 and f"{calib}: calibrated for 128x72, the frames are 64x48" in errors[0], marker.stderr
