"""``room``: the chessboard poster lands where the ground truth projects it; boxes hide what is behind them."""

import cv2
import numpy as np
import pytest

from services.detection.markers.detector import MarkerDetector
from services.geometry.camera import project_points
from services.geometry.se3 import invert, transform_points
from services.synthetic import make_scene
from services.synthetic.compositing import render_faces
from services.synthetic.room import BOXES, CHECKER_INNER, HEIGHT_M, LENGTH_M, WIDTH_M

MARGIN_PX = 20


@pytest.fixture(scope="module")
def scene():
    return make_scene("room")


def in_view(camera, points_cam: np.ndarray, margin: float) -> np.ndarray:
    """(N,) whether each camera-frame point is in front and projects ``margin`` px inside the image."""
    pixels = project_points(points_cam, camera.K)
    inside = (pixels >= margin) & (pixels <= (camera.width - 1 - margin, camera.height - 1 - margin))
    return (points_cam[:, 2] > 0.3) & inside.all(axis=1)


def test_checker_corners_match_ground_truth(scene):
    camera = scene.cameras[0]
    indices = [i for i in range(0, 1500, 5) if in_view(
        camera, transform_points(invert(scene.camera_pose(i)), scene.checker_corners), MARGIN_PX).all()]
    assert len(indices) > 20
    errors = []
    for index in indices[::len(indices) // 4][:4]:
        frame = scene.render(index)
        found, detected = cv2.findChessboardCornersSB(frame.images["cam0"], CHECKER_INNER,
                                                      flags=cv2.CALIB_CB_NORMALIZE_IMAGE)
        assert found, index
        (_, _, T_world_cam), = frame.truth["cam0"]
        expected = project_points(transform_points(invert(T_world_cam), scene.checker_corners), camera.K)
        detected = detected.reshape(-1, 2)
        residual = min(np.linalg.norm(detected - expected, axis=1), np.linalg.norm(detected[::-1] - expected, axis=1),
                       key=np.median)
        errors.extend(residual)
    assert np.median(errors) < 0.15 and np.max(errors) < 0.6


def test_box_hides_the_wall_behind_it(scene):
    """Find a frame where a box side's centre is in view; that pixel must show the box, not the wall behind."""
    camera = scene.cameras[0]
    boxes = [f for f in scene.faces if f.name.startswith("box") and not f.name.endswith("top")]
    checked = 0
    for index in range(0, 900, 15):
        T_cam_world = invert(scene.camera_pose(index))
        for face in boxes:
            centre_cam = transform_points(T_cam_world, face.T_world_face[:3, 3])
            facing = face.T_world_face[:3, 2] @ (scene.camera_pose(index)[:3, 3] - face.T_world_face[:3, 3]) > 0.3
            if not (facing and in_view(camera, centre_cam, 40)[0]):
                continue
            u, v = np.round(project_points(centre_cam, camera.K)[0]).astype(int)
            window = (slice(v - 3, v + 4), slice(u - 3, u + 4))
            rendered = scene.render(index).images["cam0"][window].astype(int)
            size = (camera.width, camera.height)
            box_alone = render_faces([face], camera.K, T_cam_world, size, 0)[window]
            shell = [f for f in scene.faces if not f.name.startswith("box")]
            behind = render_faces(shell, camera.K, T_cam_world, size, 0)[window]
            assert np.array_equal(rendered, box_alone), (index, face.name)
            assert np.abs(rendered - behind).mean() > 3, (index, face.name)
            checked += 1
    assert checked >= 5


def test_depth_order_does_not_depend_on_face_order(scene):
    camera = scene.cameras[0]
    T_cam_world = invert(scene.camera_pose(120))
    size = (camera.width, camera.height)
    forward = render_faces(scene.faces, camera.K, T_cam_world, size, 0)
    backward = render_faces(scene.faces[::-1], camera.K, T_cam_world, size, 0)
    assert np.mean(forward != backward) < 0.002  # only pixels on shared edges may differ


def test_camera_walks_inside_the_room_above_the_boxes(scene):
    poses = np.array([scene.camera_pose(i) for i in range(0, 3000, 5)])
    eyes = poses[:, :3, 3]
    assert np.all(np.abs(eyes[:, 0]) < LENGTH_M / 2 - 1.0) and np.all(np.abs(eyes[:, 1]) < WIDTH_M / 2 - 1.0)
    assert np.all(eyes[:, 2] > max(size[2] for _, size in BOXES) + 0.2) and np.all(eyes[:, 2] < HEIGHT_M - 0.5)
    assert np.ptp(eyes[:, 0]) > 1.5 and np.ptp(eyes[:, 1]) > 1.0
    headings = np.unwrap(np.arctan2(poses[:, 1, 2], poses[:, 0, 2]))
    assert np.ptp(headings) > np.pi
    steps = np.linalg.norm(np.diff(eyes, axis=0), axis=1) / 5
    assert steps.max() < 0.05  # metres per frame at 30 fps: smooth enough to track


def test_the_loop_path_goes_round_the_room_and_ends_where_it_began(scene):
    loop = make_scene("room", path="loop", loop_s=20.0, fps=15.0)
    poses = np.array([loop.camera_pose(i) for i in range(301)])
    np.testing.assert_allclose(poses[300], poses[0], atol=1e-9)
    eyes = poses[:, :3, 3]
    assert np.all(np.abs(eyes[:, 0]) < LENGTH_M / 2 - 1.0) and np.all(np.abs(eyes[:, 1]) < WIDTH_M / 2 - 1.0)
    headings = np.unwrap(np.arctan2(poses[:, 1, 2], poses[:, 0, 2]))
    assert headings[-1] - headings[0] == pytest.approx(2 * np.pi)
    assert np.linalg.norm(np.diff(eyes, axis=0), axis=1).max() < 0.05
    assert np.array_equal(make_scene("room", path="sine").camera_pose(123), scene.camera_pose(123))


def test_faces_cover_the_view_with_at_most_a_few_seam_pixels(scene):
    camera = scene.cameras[0]
    size = (camera.width, camera.height)
    for index in (0, 333, 666):
        T_cam_world = invert(scene.camera_pose(index))
        black, white = (render_faces(scene.faces, camera.K, T_cam_world, size, background) for background in (0, 255))
        assert np.count_nonzero(black != white) < 0.001 * black.size


def test_default_room_has_no_marker(scene):
    assert scene.T_world_marker is None and scene.fixtures().settings == {}
    assert "marker" not in [face.name for face in scene.faces]
    assert [child for _, child, _ in scene.render(90).truth["cam0"]] == ["cam0"]


def test_marker_corners_match_ground_truth():
    scene = make_scene("room", marker=True, marker_id=7, marker_length=0.3)
    camera = scene.cameras[0]
    detector = MarkerDetector("DICT_4X4_50")
    seen = errors = 0
    for index in range(0, 300, 6):
        frame = scene.render(index)
        truths = {child: T for _, child, T in frame.truth["cam0"]}
        detections = detector.detect(frame.images["cam0"], camera.K)
        found = dict(zip(detections.ids.tolist(), detections.corners, strict=True))
        assert set(found) <= {7}, index
        if "marker/7" not in truths:
            continue
        assert 7 in found, index
        expected = project_points(transform_points(truths["marker/7"], scene.marker_corners), camera.K)
        errors = max(errors, float(np.max(np.linalg.norm(found[7].reshape(4, 2) - expected, axis=1))))
        seen += 1
    assert seen >= 20 and errors < 0.15
    T_cam_marker = invert(scene.camera_pose(90)) @ scene.T_world_marker
    assert np.allclose(dict((c, T) for _, c, T in scene.render(90).truth["cam0"])["marker/7"], T_cam_marker)
    assert scene.fixtures().settings == {"marker_length": 0.3, "dictionary": "DICT_4X4_50"}


@pytest.mark.parametrize(("options", "message"), [
    ({"marker": 1}, "marker=1"),
    ({"marker_id": 50}, r"marker_id=50: .*\[0, 49\]"),
    ({"marker_dictionary": "DICT_5X5_2"}, "marker_dictionary='DICT_5X5_2'"),
    ({"marker_length": 0.0}, "marker_length=0.0"),
    ({"path": "circle"}, "path='circle'"),
])
def test_invalid_marker_options_are_rejected(options, message):
    with pytest.raises(ValueError, match=f"option {message}"):
        make_scene("room", **options)


def test_a_room_asked_for_its_cameras_and_fixtures_draws_no_texture():
    """The launcher's checks build the scene for its cameras and fixtures; its textures wait for a frame."""
    room = make_scene("room", marker=True)
    assert room.cameras[0].name == "cam0" and room.fixtures().settings
    assert "faces" not in vars(room)
    room.render(0)
    assert [face.name for face in vars(room)["faces"]][-1] == "marker"
