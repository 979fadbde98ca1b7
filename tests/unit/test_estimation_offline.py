"""The offline API: marker poses of rendered frames against their ground truth, of a folder, and of real photos."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from services.calibration.camera_info import write_camera_info
from services.detection.markers.sheet import board_document
from services.estimation.markers.map import map_from_poses, parse_marker_map
from services.estimation.markers.offline import track_folder, track_images
from services.geometry.camera import CameraModel
from services.geometry.rotation import rotation_angle
from services.geometry.se3 import invert
from services.synthetic import make_scene
from tests.accuracy.charuco_photos import CALIBRATION, DATA_SET, DICTIONARY, MARKER_M, SQUARE_M, SQUARES, intrinsics
from tests.data import data_dir

LENGTH = 0.05
FRAMES = 12


@pytest.fixture(scope="module")
def rendered():
    """``FRAMES`` frames of the markers scene, its camera, its per-frame truth and the scene."""
    scene = make_scene("markers", marker_length=LENGTH)
    frames = [scene.render(i) for i in range(FRAMES)]
    camera = scene.cameras[0]
    truth = [{child: T for _, child, T in frame.truth[camera.name]} for frame in frames]
    return [frame.images[camera.name] for frame in frames], camera, truth, scene


def pose_errors(T: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    """(rotation error deg, translation error as a fraction of the true distance)."""
    rotation = np.degrees(rotation_angle(T[:3, :3], T_true[:3, :3]))
    return rotation, float(np.linalg.norm(T[:3, 3] - T_true[:3, 3]) / np.linalg.norm(T_true[:3, 3]))


def test_rendered_frames_give_the_true_marker_poses(rendered):
    images, camera, truth, _ = rendered
    frames = list(track_images(images, camera, marker_length=LENGTH))
    assert [f.index for f in frames] == list(range(FRAMES))
    scored = []
    for frame, known in zip(frames, truth, strict=True):
        assert set(known) <= set(frame.poses)
        for target, T_true in known.items():
            pose = frame.poses[target]
            assert pose.state == "tracking" and pose.reprojection_rms_px < 0.5 and pose.corners == 4
            assert pose.covariance is not None and pose.covariance.shape == (6, 6)
            scored.append(pose_errors(pose.T_camera_target, T_true))
    errors = np.array(scored)
    assert len(errors) >= 3 * FRAMES
    assert np.median(errors[:, 0]) < 0.5 and np.median(errors[:, 1]) < 0.005, errors


def test_a_board_gets_one_pose_and_a_lost_target_is_reported_once(rendered):
    images, camera, truth, scene = rendered
    board = map_from_poses("board", scene.marker_poses, LENGTH, "DICT_4X4_50")
    blank = np.full_like(images[0], 128)
    frames = list(track_images([images[0], images[1], blank, blank], camera, board=board))
    for frame, known in zip(frames[:2], truth, strict=False):
        assert set(frame.poses) == {"board"}
        marker_id, T_cam_marker = next((int(k.split("/")[1]), T) for k, T in known.items())
        T_true = T_cam_marker @ invert(scene.marker_poses[marker_id])
        rotation, translation = pose_errors(frame.poses["board"].T_camera_target, T_true)
        assert rotation < 0.3 and translation < 0.003
    assert {t: p.state for t, p in frames[2].poses.items()} == {"board": "lost"}
    np.testing.assert_array_equal(frames[2].poses["board"].T_camera_target, np.eye(4))
    assert frames[3].poses == {} and len(frames[3].detections) == 0


def test_a_folder_tracks_as_its_images_do(rendered, tmp_path):
    images, camera, _, _ = rendered
    for n, image in enumerate(images[:4]):
        cv2.imwrite(str(tmp_path / f"{n:03d}.png"), image)
    (tmp_path / "notes.txt").write_text("not an image")
    calib = tmp_path / "cam0.yaml"
    write_camera_info(calib, camera)
    from_folder = list(track_folder(tmp_path, calib, marker_length=LENGTH))
    in_memory = list(track_images(images[:4], camera, marker_length=LENGTH))
    assert [f.path.name for f in from_folder] == ["000.png", "001.png", "002.png", "003.png"]
    for a, b in zip(from_folder, in_memory, strict=True):
        assert a.poses.keys() == b.poses.keys()
        for target in a.poses:
            np.testing.assert_allclose(a.poses[target].T_camera_target, b.poses[target].T_camera_target, atol=1e-9)


def test_bad_options_fail_at_the_call(rendered, tmp_path):
    images, camera, _, _ = rendered
    with pytest.raises(ValueError, match="marker_lenght"):
        track_images(images, camera, marker_lenght=0.05)
    with pytest.raises(ValueError, match="unknown marker dictionary"):
        track_images(images, camera, dictionary="DICT_9X9_1")
    with pytest.raises(ValueError, match="missing.yaml"):
        track_images(images, tmp_path / "missing.yaml")
    with pytest.raises(ValueError, match="no such folder"):
        track_folder(tmp_path / "nowhere", camera)


def test_real_charuco_photos_with_a_printed_board_file(tmp_path):
    """OpenCV's ChArUco tutorial photos, tracked with the board file ``artrack markers print`` writes for that
    board; the reference is cv2.solvePnP on the ChArUco corners (the data set has no ground-truth poses)."""
    folder = data_dir(DATA_SET)
    K, dist = intrinsics(folder / CALIBRATION)
    for name in ("img_00.jpg", "img_01.jpg", "img_02.jpg", "img_03.jpg"):
        (tmp_path / name).symlink_to(folder / name)
    calib = tmp_path / "camera.yaml"
    write_camera_info(calib, CameraModel("cam0", 640, 480, K, dist, np.eye(4)))
    dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, DICTIONARY))
    charuco = cv2.aruco.CharucoBoard(SQUARES, SQUARE_M, MARKER_M, dictionary)
    board = parse_marker_map(board_document(charuco, "charuco", DICTIONARY))
    detector = cv2.aruco.CharucoDetector(charuco)
    centre = np.array([SQUARES[0], SQUARES[1], 0]) * SQUARE_M / 2
    frames = list(track_folder(tmp_path, calib, board=board))
    assert len(frames) == 4
    for frame in frames:
        pose = frame.poses["charuco"]
        assert pose.state == "tracking" and pose.reprojection_rms_px < 1.0
        grey = cv2.imread(str(frame.path), cv2.IMREAD_GRAYSCALE)
        corners, ids, _, _ = detector.detectBoard(grey)
        board_points, image_points = charuco.matchImagePoints(corners, ids)
        ours = (board_points.reshape(-1, 3) - centre) * [1, -1, -1]  # OpenCV's board frame: y down, z into it
        ok, rvec, tvec = cv2.solvePnP(ours, image_points.reshape(-1, 2), K, dist)
        assert ok
        T_ref = np.eye(4)
        T_ref[:3, :3], T_ref[:3, 3] = cv2.Rodrigues(rvec)[0], tvec.ravel()
        rotation, _ = pose_errors(pose.T_camera_target, T_ref)
        assert rotation < 1.0 and np.linalg.norm(pose.T_camera_target[:3, 3] - T_ref[:3, 3]) < 0.003
