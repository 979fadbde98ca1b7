"""Calibration on rendered boards: a known camera is recovered, and sets that cannot constrain it are refused."""

import cv2
import numpy as np
import pytest

from services.calibration.camera_info import CalibrationError as CalibrationFileError
from services.calibration.camera_info import fit_to_image
from services.calibration.intrinsics import (
    MIN_TILT_SPREAD_DEG,
    CalibrationError,
    Charuco,
    Chessboard,
    board_normals,
    calibrate,
    calibrate_images,
    find_views,
    tilt_spread_deg,
)
from services.geometry.camera import CameraModel, project_points
from services.geometry.rotation import matrix_from_rotvec
from services.geometry.se3 import transform_points
from tests.chessboard_images import TEXELS, board_centre, chessboard_texture, render_board

SIZE = (640, 480)
K_TRUE = np.array([[620.0, 0.0, 331.0], [0.0, 612.0, 236.0], [0.0, 0.0, 1.0]])
CHESSBOARD = Chessboard(9, 6, 0.025)


def charuco_texture(board: Charuco) -> tuple[np.ndarray, np.ndarray]:
    """The ChArUco board image (OpenCV's drawing) and the (3, 3) map from board metres to its texels."""
    cv_board = cv2.aruco.CharucoBoard((board.columns, board.rows), board.square_m, board.marker_m,
                                      cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, board.dictionary)))
    margin = TEXELS
    image = cv_board.generateImage((board.columns * TEXELS + 2 * margin, board.rows * TEXELS + 2 * margin),
                                   marginSize=margin)
    scale = TEXELS / board.square_m
    return image, np.array([[scale, 0.0, margin - 0.5], [0.0, scale, margin - 0.5], [0.0, 0.0, 1.0]])


def render(texture: np.ndarray, texel_from_board: np.ndarray, R: np.ndarray, t: np.ndarray,
           distortion_map: tuple[np.ndarray, np.ndarray] | None = None, seed: int = 0) -> np.ndarray:
    """The board seen by a camera K_TRUE with ``T_camera_board = [R | t]``, grey background, mild noise."""
    return render_board(texture, texel_from_board, K_TRUE, R, t, SIZE, distortion_map, seed)


def distortion_map(dist: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """remap() maps: for every pixel of the distorted image, where it comes from in the ideal one."""
    u, v = np.meshgrid(np.arange(SIZE[0], dtype=np.float32), np.arange(SIZE[1], dtype=np.float32))
    distorted = np.stack([u.ravel(), v.ravel()], axis=1).reshape(-1, 1, 2)
    ideal = cv2.undistortPoints(distorted, K_TRUE, dist, P=K_TRUE).reshape(SIZE[1], SIZE[0], 2)
    return ideal[..., 0].copy(), ideal[..., 1].copy()


def distortion_error_px(camera, dist_true: np.ndarray) -> float:
    """Largest difference (px) between the shifts the fitted and the true distortion make, within 70 % of the
    half-diagonal from the image centre (the views reach about 80 %; beyond the data k3 extrapolates freely)."""
    u, v = np.meshgrid(np.linspace(0, SIZE[0] - 1, 33), np.linspace(0, SIZE[1] - 1, 25))
    inside = np.hypot(u - SIZE[0] / 2, v - SIZE[1] / 2) <= 0.7 * np.hypot(*SIZE) / 2
    rays = (np.linalg.inv(K_TRUE) @ np.stack([u[inside], v[inside], np.ones(inside.sum())])).T
    fitted = project_points(rays, camera.K, camera.dist) - project_points(rays, camera.K)
    true = project_points(rays, K_TRUE, dist_true) - project_points(rays, K_TRUE)
    return float(np.linalg.norm(fitted - true, axis=1).max())


def pose(board, rotvec, distance: float, shift=(0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) of a board turned by ``rotvec`` whose centre sits ``distance`` m ahead, moved by ``shift`` m."""
    R = matrix_from_rotvec(np.asarray(rotvec, dtype=np.float64))
    return R, np.array([shift[0], shift[1], distance]) - R @ board_centre(board)


def views_of(board, poses, dist=None) -> list[tuple[str, np.ndarray]]:
    texture, texel_from_board = chessboard_texture(board) if isinstance(board, Chessboard) else charuco_texture(board)
    remap = None if dist is None else distortion_map(dist)
    return [(f"view{i:02d}.png", render(texture, texel_from_board, R, t, remap, seed=i))
            for i, (R, t) in enumerate(poses)]


def tilted_poses(board, count: int, seed: int = 1) -> list[tuple[np.ndarray, np.ndarray]]:
    """Views tilted 15 to 40 deg about varied in-plane axes, turned in plane, at 0.35 to 0.45 m, off centre
    by up to 8 cm so that the corners of the image see the board too."""
    rng = np.random.default_rng(seed)
    poses = []
    for i in range(count):
        axis_angle = 2 * np.pi * i / count + rng.uniform(-0.3, 0.3)
        tilt = np.radians(rng.uniform(15, 40))
        tilt_axis = np.array([np.cos(axis_angle), np.sin(axis_angle), 0.0])
        R_tilt = matrix_from_rotvec(tilt * tilt_axis)
        R_spin = matrix_from_rotvec(np.array([0.0, 0.0, rng.uniform(-0.4, 0.4)]))
        R = R_tilt @ R_spin
        centre = np.array([rng.uniform(-0.08, 0.08), rng.uniform(-0.06, 0.06), rng.uniform(0.35, 0.45)])
        poses.append((R, centre - R @ board_centre(board)))
    return poses


def test_chessboard_views_recover_the_camera():
    images = views_of(CHESSBOARD, tilted_poses(CHESSBOARD, 12))
    result = calibrate_images(images, CHESSBOARD, name="left")
    K = result.camera.K
    assert result.camera.name == "left" and (result.camera.width, result.camera.height) == SIZE
    assert len(result.views) == 12 and result.skipped == ()
    assert K[0, 0] == pytest.approx(620, rel=0.01) and K[1, 1] == pytest.approx(612, rel=0.01)
    assert abs(K[0, 2] - 331) < 3 and abs(K[1, 2] - 236) < 3
    assert distortion_error_px(result.camera, np.zeros(5)) < 0.5
    assert result.rms_px < 0.2 and result.tilt_spread_deg > 30
    assert np.all(result.std_px < 2.0)


def test_per_view_rms_and_poses_reproject_the_corners():
    result = calibrate_images(views_of(CHESSBOARD, tilted_poses(CHESSBOARD, 6, seed=4)), CHESSBOARD)
    camera = result.camera
    squared = []
    for view, rms, T in zip(result.views, result.view_rms_px, result.T_camera_board, strict=True):
        residual = project_points(transform_points(T, view.board_points), camera.K, camera.dist) - view.image_points
        assert rms == pytest.approx(np.sqrt(np.mean(np.sum(residual**2, axis=1))), rel=1e-3)
        squared.extend(np.sum(residual**2, axis=1))
    assert result.rms_px == pytest.approx(np.sqrt(np.mean(squared)), rel=1e-3)


def test_lens_distortion_is_recovered():
    dist = np.array([-0.25, 0.08, 0.0, 0.0, 0.0])
    result = calibrate_images(views_of(CHESSBOARD, tilted_poses(CHESSBOARD, 14, seed=2), dist), CHESSBOARD)
    K = result.camera.K
    assert K[0, 0] == pytest.approx(620, rel=0.01) and K[1, 1] == pytest.approx(612, rel=0.01)
    assert distortion_error_px(result.camera, dist) < 0.5
    assert result.rms_px < 0.3


def test_charuco_views_recover_the_camera():
    board = Charuco(5, 7, 0.04, 0.02, "DICT_6X6_250")
    result = calibrate_images(views_of(board, tilted_poses(board, 10, seed=3)), board)
    K = result.camera.K
    assert len(result.views) == 10 and all(len(v.image_points) >= 12 for v in result.views)
    assert K[0, 0] == pytest.approx(620, rel=0.01) and K[1, 1] == pytest.approx(612, rel=0.01)
    assert abs(K[0, 2] - 331) < 3 and abs(K[1, 2] - 236) < 3


def test_fronto_parallel_views_are_refused():
    poses = [pose(CHESSBOARD, (0.0, 0.0, spin), distance, shift)
             for spin, distance, shift in [(-0.4, 0.42, (0.0, 0.0)), (0.0, 0.45, (0.03, 0.01)),
                                           (0.3, 0.5, (-0.03, 0.02)), (0.6, 0.44, (0.02, -0.02)),
                                           (-0.2, 0.55, (-0.02, -0.01)), (1.0, 0.48, (0.0, 0.02))]]
    views, _, size = find_views(views_of(CHESSBOARD, poses), CHESSBOARD)
    assert len(views) == 6
    assert tilt_spread_deg(board_normals(views, size)) < 1.0
    with pytest.raises(CalibrationError, match="nearly parallel"):
        calibrate(views, size)


def test_parallel_tilted_views_are_refused():
    R_tilt = matrix_from_rotvec(np.array([0.5, 0.2, 0.0]))
    poses = []
    for i, spin in enumerate((-0.4, -0.1, 0.2, 0.5, 0.8)):
        R = R_tilt @ matrix_from_rotvec(np.array([0.0, 0.0, spin]))
        poses.append((R, np.array([0.01 * i - 0.02, 0.0, 0.33 + 0.03 * i]) - R @ board_centre(CHESSBOARD)))
    views, _, size = find_views(views_of(CHESSBOARD, poses), CHESSBOARD)
    assert len(views) == 5
    normals = board_normals(views, size)
    assert np.degrees(np.arccos(-normals[:, 2])).min() > 25  # every view is well tilted, all the same way
    with pytest.raises(CalibrationError, match=f"tilt spread .* < {MIN_TILT_SPREAD_DEG:.0f} deg"):
        calibrate(views, size)


def test_too_few_views_are_refused_naming_the_skipped_images():
    images = views_of(CHESSBOARD, tilted_poses(CHESSBOARD, 2))
    images.append(("blank.png", np.full(SIZE[::-1], 200, np.uint8)))
    with pytest.raises(CalibrationError, match=r"only 2 usable view\(s\) \(skipped: blank.png\); at least 3"):
        calibrate_images(images, CHESSBOARD)


def test_a_wrong_pattern_size_is_refused():
    images = views_of(CHESSBOARD, tilted_poses(CHESSBOARD, 3))
    with pytest.raises(CalibrationError, match="chessboard of 8x6 inner corners was found in none of the 3 images"):
        calibrate_images(images, Chessboard(8, 6, 0.025))


def test_unreadable_and_odd_sized_images_are_skipped_with_reasons():
    images = views_of(CHESSBOARD, tilted_poses(CHESSBOARD, 4))
    images.insert(1, ("broken.jpg", None))
    images.append(("small.png", np.zeros((240, 320), np.uint8)))
    result = calibrate_images(images, CHESSBOARD)
    assert [v.name for v in result.views] == ["view00.png", "view01.png", "view02.png", "view03.png"]
    assert dict(result.skipped) == {"broken.jpg": "cannot be read as an image",
                                    "small.png": "size 320x240 differs from the first image's 640x480"}
    report = result.report()
    assert "broken.jpg: skipped" in report and "view02.png: rms" in report and "4 views, 216 points" in report


def test_tilt_spread_is_the_largest_angle_between_normals():
    normals = np.array([[0.0, 0.0, -1.0], [np.sin(0.2), 0.0, -np.cos(0.2)], [0.0, -np.sin(0.3), -np.cos(0.3)]])
    expected = np.degrees(np.arccos(normals[1] @ normals[2]))
    assert tilt_spread_deg(normals) == pytest.approx(expected)
    assert tilt_spread_deg(normals[:1]) == 0.0


def test_bad_targets_are_refused():
    with pytest.raises(ValueError, match="2x2 inner corners"):
        Chessboard(1, 6, 0.025)
    with pytest.raises(ValueError, match="marker < square"):
        Charuco(5, 7, 0.04, 0.05, "DICT_6X6_250")
    with pytest.raises(ValueError, match="unknown marker dictionary"):
        Charuco(5, 7, 0.04, 0.02, "DICT_9X9_1")


def test_fit_to_image_scales_intrinsics_as_resizing_moves_pixels():
    K = np.array([[900.0, 0.0, 641.3], [0.0, 905.0, 357.9], [0.0, 0.0, 1.0]])
    dist = np.array([-0.21, 0.05, 0.001, -0.002, 0.01])
    hd = CameraModel("cam0", 1280, 720, K, dist, np.eye(4))
    same, nothing = fit_to_image(hd, 1280, 720, "hd.yaml")
    assert same is hd and nothing is None
    small, note = fit_to_image(hd, 640, 360, "hd.yaml")
    assert note == "hd.yaml: calibrated for 1280x720, the frames are 640x360: intrinsics scaled by 0.5 (fx, fy, cx, " \
                   "cy; distortion unchanged)"
    assert (small.width, small.height) == (640, 360) and np.array_equal(small.dist, dist)
    rng = np.random.default_rng(4)
    points = np.column_stack([rng.uniform(-1, 1, (50, 2)), rng.uniform(2, 5, 50)])
    at_hd, _ = cv2.projectPoints(points, np.zeros(3), np.zeros(3), K, dist)
    at_small, _ = cv2.projectPoints(points, np.zeros(3), np.zeros(3), small.K, small.dist)
    # cv2.resize by 1/2 maps pixel u to (u + 0.5) / 2 - 0.5 (pixel centres at integer coordinates)
    np.testing.assert_allclose(at_small.reshape(-1, 2), (at_hd.reshape(-1, 2) + 0.5) / 2 - 0.5, atol=1e-9)


def test_fit_to_image_refuses_another_aspect_ratio_naming_both_sizes_and_the_file():
    hd = CameraModel("cam0", 1280, 720, np.array([[900.0, 0, 640], [0, 900, 360], [0, 0, 1]]), np.zeros(5), np.eye(4))
    with pytest.raises(CalibrationFileError, match=r"^hd.yaml: calibrated for 1280x720, the frames are 640x480 "
                                               r"\(another aspect ratio\)"):
        fit_to_image(hd, 640, 480, "hd.yaml")
