"""The capture node as a real process: files and scenes in, frames on their keys out."""

import cv2
import numpy as np

from protocol import CameraInfo, GroundTruth, Image
from services.bus.pubsub import Inbox, Role
from services.calibration.camera_info import write_camera_info
from services.geometry.camera import CameraModel
from tests.integration.support import START_S, collect, start_node


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
        start_node(procs, "capture", "rig", source="synthetic:ir_rig", frames=4, fps=20, wait_for_subscriber=True)
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
