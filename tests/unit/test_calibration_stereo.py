"""Stereo calibration on boards rendered into two cameras of a known rig: the pose between them is recovered,
the rig file holds it, and sets that cannot calibrate the pair are refused naming why."""

import hashlib
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from services.calibration.intrinsics import CalibrationError, Chessboard
from services.calibration.rig import read_rig, write_rig
from services.calibration.stereo import MIN_PAIRS, calibrate_stereo, find_pairs, fit_stereo
from services.geometry.rotation import matrix_from_rotvec, rotation_angle
from services.geometry.se3 import invert, make_transform
from tests.chessboard_images import board_centre, chessboard_texture, render_board

SIZE = (640, 480)
K_LEFT = np.array([[620.0, 0.0, 331.0], [0.0, 612.0, 236.0], [0.0, 0.0, 1.0]])
K_RIGHT = np.array([[580.0, 0.0, 315.0], [0.0, 583.0, 244.0], [0.0, 0.0, 1.0]])
T_LEFT_RIGHT = make_transform(matrix_from_rotvec(np.radians([1.5, -4.0, 0.8])), np.array([0.08, 0.003, -0.004]))
"""The right camera's pose in the left camera's frame: 8 cm to its right, turned 4.4 deg towards it."""
PAIRS = 20


class RecalledChessboard(Chessboard):
    """A chessboard whose corners are searched once per distinct image in this module: the same rendered
    pairs go through several calibrations (and every blank image is the same), and the search is most of
    a calibration's time. ``find`` answers what ``Chessboard.find`` answered for the same pixels."""

    found: dict[tuple[tuple[int, ...], str], tuple[np.ndarray, np.ndarray] | None] = {}

    def find(self, grey: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        key = (grey.shape, hashlib.sha256(grey.tobytes()).hexdigest())
        if key not in self.found:
            self.found[key] = super().find(grey)
        answer = self.found[key]
        return None if answer is None else (answer[0].copy(), answer[1].copy())


BOARD = RecalledChessboard(9, 6, 0.025)


def board_poses(count: int, seed: int = 1) -> list[np.ndarray]:
    """``T_left_board`` (4, 4): tilted 20 to 45 deg about varied axes, turned in plane, centred near the middle
    of the two cameras 0.3 to 0.45 m ahead (a few views leave one camera's image: those pairs are rejected)."""
    rng = np.random.default_rng(seed)
    poses = []
    for i in range(count):
        axis_angle = 2 * np.pi * i / count + rng.uniform(-0.3, 0.3)
        tilt = np.radians(rng.uniform(20, 45))
        R = matrix_from_rotvec(tilt * np.array([np.cos(axis_angle), np.sin(axis_angle), 0.0])) @ \
            matrix_from_rotvec(np.array([0.0, 0.0, rng.uniform(-0.4, 0.4)]))
        centre = np.array([0.04 + rng.uniform(-0.03, 0.03), rng.uniform(-0.02, 0.02), rng.uniform(0.3, 0.45)])
        poses.append(make_transform(R, centre - R @ board_centre(BOARD)))
    return poses


def pairs_of(poses: list[np.ndarray]) -> tuple[list, list]:
    """Named left and right images of the board at ``T_left_board`` poses."""
    texture, texel_from_board = chessboard_texture(BOARD)
    left, right = [], []
    for i, T_left_board in enumerate(poses):
        T_right_board = invert(T_LEFT_RIGHT) @ T_left_board
        for images, K, T, prefix in ((left, K_LEFT, T_left_board, "left"), (right, K_RIGHT, T_right_board, "right")):
            image = render_board(texture, texel_from_board, K, T[:3, :3], T[:3, 3], SIZE, seed=2 * i + len(images))
            images.append((f"{prefix}{i:02d}.png", image))
    return left, right


@pytest.fixture(scope="module")
def rendered() -> tuple[list, list]:
    return pairs_of(board_poses(PAIRS))


@pytest.fixture(scope="module")
def stereo(rendered):
    return calibrate_stereo(*rendered, BOARD, names=("left", "right"))


def pose_errors(T_left_right: np.ndarray) -> tuple[float, float]:
    """(metres, degrees) between ``T_left_right`` and the true one."""
    return (float(np.linalg.norm(T_left_right[:3, 3] - T_LEFT_RIGHT[:3, 3])),
            float(np.degrees(rotation_angle(T_left_right[:3, :3], T_LEFT_RIGHT[:3, :3]))))


def principal_point_bound_deg(stereo) -> float:
    """Three sigma of the rotation error the principal points' uncertainty alone causes: a principal point off
    by d px turns its camera's frame by d / f rad, for each camera and both axes."""
    turns = [std[2:] / np.diag(calibration.camera.K)[:2]
             for calibration, std in ((stereo.first, stereo.first.std_px), (stereo.second, stereo.second.std_px))]
    return float(np.degrees(3 * np.linalg.norm(np.concatenate(turns))))


@pytest.mark.slow
def test_the_rig_is_recovered(stereo):
    assert len(stereo.pairs) == PAIRS and stereo.rejected == ()
    offset_m, angle_deg = pose_errors(invert(stereo.T_second_first))
    assert offset_m < 0.001
    # from images alone the rotation is as good as the principal points (one-sigma about 0.4 px here)
    assert angle_deg < principal_point_bound_deg(stereo) < 0.25
    assert stereo.baseline_m == pytest.approx(np.linalg.norm(T_LEFT_RIGHT[:3, 3]), abs=0.001)
    assert stereo.rms_px < 0.2 and stereo.pair_rms_px.shape == (PAIRS, 2) and np.all(stereo.pair_rms_px < 0.3)
    assert stereo.first.camera.K[0, 0] == pytest.approx(620, rel=0.01)
    assert stereo.second.camera.K[0, 0] == pytest.approx(580, rel=0.01)


def test_with_the_true_intrinsics_the_pose_is_exact(stereo):
    fit = fit_stereo(stereo.pairs, replace(stereo.first.camera, K=K_LEFT, dist=np.zeros(5)),
                     replace(stereo.second.camera, K=K_RIGHT, dist=np.zeros(5)))
    offset_m, angle_deg = pose_errors(invert(fit.T_second_first))
    assert offset_m < 0.001 and angle_deg < 0.05
    np.testing.assert_array_equal(fit.first.K, K_LEFT)  # fixed intrinsics stay as given


def test_corners_fall_on_one_row_after_rectification(stereo):
    errors = stereo.row_errors_px()
    assert errors is not None and len(errors) == PAIRS * 54
    assert np.sqrt(np.mean(errors ** 2)) < 0.2
    held_out, rejected = find_pairs(*pairs_of(board_poses(3, seed=7)), BOARD)
    assert len(held_out) == 3 and rejected == []
    held_out_errors = stereo.row_errors_px(held_out)
    assert held_out_errors is not None and np.sqrt(np.mean(held_out_errors ** 2)) < 0.3


@pytest.mark.slow
def test_refined_intrinsics_keep_the_rig(rendered):
    refined = calibrate_stereo(*rendered, BOARD, refine_intrinsics=True)
    offset_m, angle_deg = pose_errors(invert(refined.T_second_first))
    assert refined.refined and offset_m < 0.001 and angle_deg < principal_point_bound_deg(refined)
    assert refined.second.camera.K[0, 0] == pytest.approx(580, rel=0.01)


def test_the_rig_file_reads_back_in_either_cameras_frame(stereo, tmp_path: Path):
    for frame, T_rig_left in ((None, np.eye(4)), ("right", invert(T_LEFT_RIGHT))):
        path = tmp_path / f"rig-{frame}.yaml"
        write_rig(path, stereo.rig("bench", frame))
        rig = read_rig(path)
        assert rig.name == "bench" and rig.names == ("left", "right")
        left, right = rig.camera("left"), rig.camera("right")
        np.testing.assert_allclose(left.K, stereo.first.camera.K)
        np.testing.assert_allclose(right.dist, stereo.second.camera.dist)
        np.testing.assert_allclose(left.T_rig_camera, T_rig_left, atol=3e-3)
        np.testing.assert_allclose(invert(left.T_rig_camera) @ right.T_rig_camera, invert(stereo.T_second_first),
                                   atol=1e-9)
    with pytest.raises(CalibrationError, match="rig frame 'middle' is none of the cameras"):
        stereo.rig("bench", "middle")


def test_report_is_a_table_of_both_cameras_and_the_pose(stereo):
    report = stereo.report()
    assert "left00.png + right00.png: rms" in report
    for row in ("camera         left", f"pairs used     {PAIRS} of {PAIRS}", "baseline m     0.080",
                "rotation deg   4.", "epipolar px"):
        assert row in report, report


def test_unequal_counts_are_refused(rendered):
    left, right = rendered
    with pytest.raises(CalibrationError, match=f"{PAIRS} images of cam0 but {PAIRS - 1} of cam1"):
        calibrate_stereo(left, right[:-1], BOARD)


@pytest.mark.slow
def test_a_camera_that_never_sees_the_board_is_refused(rendered):
    left, right = rendered
    blank = [(name, np.full(SIZE[::-1], 200, np.uint8)) for name, _ in right]
    with pytest.raises(CalibrationError, match="camera cam1: the chessboard of 9x6 inner corners was found in none"):
        calibrate_stereo(left, blank, BOARD)


@pytest.mark.slow
def test_pairs_without_the_board_in_both_views_are_rejected(rendered):
    left, right = rendered
    blank = np.full(SIZE[::-1], 200, np.uint8)
    # each camera sees the board in half the pairs, but never in the same pair as the other
    half = PAIRS // 2
    crossed_left = [(name, image if i < half else blank) for i, (name, image) in enumerate(left)]
    crossed_right = [(name, blank if i < half else image) for i, (name, image) in enumerate(right)]
    with pytest.raises(CalibrationError, match=f"only 0 pair\\(s\\) show the .* at least {MIN_PAIRS} are needed"):
        calibrate_stereo(crossed_left, crossed_right, BOARD)
    # with four good pairs, the rest are reported as rejected, naming the image without the board
    some_right = [(name, blank if 4 <= i < 8 else image) for i, (name, image) in enumerate(right)]
    stereo = calibrate_stereo(left, some_right, BOARD)
    assert len(stereo.pairs) == PAIRS - 4 and len(stereo.rejected) == 4
    assert stereo.rejected[0] == ("left04.png + right04.png", "right04.png: chessboard of 9x6 inner corners not found")


def test_one_name_for_both_cameras_is_refused(rendered):
    with pytest.raises(CalibrationError, match="distinct names"):
        calibrate_stereo(*rendered, BOARD, names=("cam", "cam"))
