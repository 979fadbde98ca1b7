"""``artrack calibrate --stereo`` on OpenCV's stereo sample pairs, compared with what is known of that rig.

SOURCE.md of calib_chessboard_stereo_opencv: 13 pairs of 640x480 images of a 9x6 chessboard whose
square is not stated; OpenCV's own stereo_calib gets a baseline of about 3.34 squares, almost all
along x, and a stereo RMS of 0.45 px with fixed intrinsics (findChessboardCorners + cornerSubPix).
With ``--square 0.025`` the baseline is 3.34 x 0.025 = 0.0835 m.

With no true pose to score against, the rig is also checked on pairs it was not calibrated on:
after rectification a corner and its match in the other image must lie on one row.
"""

import re

import cv2
import numpy as np
import pytest

from services.calibration.intrinsics import Chessboard
from services.calibration.rig import read_rig
from services.calibration.stereo import calibrate_stereo, find_pairs
from services.geometry.rotation import rotation_angle
from services.geometry.se3 import invert
from tests.data import data_dir

pytestmark = pytest.mark.integration

CHESSBOARD = ("--pattern", "chessboard", "--size", "9x6", "--square", "0.025")
BOARD = Chessboard(9, 6, 0.025)
BASELINE_M = 3.34 * 0.025
TIMEOUT_S = 180.0


def figure(stdout: str, row: str) -> float:
    found = re.search(rf"^{row} +([0-9.]+)", stdout, re.MULTILINE)
    assert found, stdout
    return float(found.group(1))


def test_stereo_pairs_give_opencvs_rig(procs, tmp_path):
    folder = data_dir("calib_chessboard_stereo_opencv")
    out = tmp_path / "stereo.yaml"
    proc = procs.run("calibrate", "--stereo", str(folder / "left*.jpg"), str(folder / "right*.jpg"), *CHESSBOARD,
                     "--names", "left,right", "--out", str(out), timeout=TIMEOUT_S)
    assert proc.poll() == 0, proc.describe()
    assert len(re.findall(r"^left\d\d\.jpg \+ right\d\d\.jpg: rms", proc.stdout, re.MULTILINE)) == 13
    assert re.search(r"^pairs used +13 of 13$", proc.stdout, re.MULTILINE), proc.stdout
    # OpenCV's figures for these images (SOURCE.md) are upper bounds: the corners found here are finer
    assert figure(proc.stdout, "stereo rms px") < 0.45
    assert figure(proc.stdout, "baseline m") == pytest.approx(BASELINE_M, rel=0.02)
    # matched corners land on one rectified row to within the corners' own precision (each camera's RMS, 0.25 px)
    assert figure(proc.stdout, "epipolar px") < 0.3
    rig = read_rig(out)
    assert rig.name == "stereo" and rig.names == ("left", "right")
    left, right = rig.camera("left"), rig.camera("right")
    np.testing.assert_allclose(left.T_rig_camera, np.eye(4))
    centre = right.T_rig_camera[:3, 3]
    assert centre[0] == pytest.approx(BASELINE_M, rel=0.02) and np.hypot(centre[1], centre[2]) < 0.002
    assert np.degrees(rotation_angle(right.T_rig_camera[:3, :3], np.eye(3))) < 2.0


def test_the_rig_frame_can_be_the_second_camera(procs, tmp_path):
    folder = data_dir("calib_chessboard_stereo_opencv")
    out = tmp_path / "rig.yaml"
    proc = procs.run("calibrate", "--stereo", str(folder / "left*.jpg"), str(folder / "right*.jpg"), *CHESSBOARD,
                     "--rig-frame", "cam1", "--refine-intrinsics", "--out", str(out), timeout=TIMEOUT_S)
    assert proc.poll() == 0, proc.describe()
    assert "intrinsics refined" in proc.stdout and "rig frame: cam1" in proc.stdout
    rig = read_rig(out)
    np.testing.assert_allclose(rig.camera("cam1").T_rig_camera, np.eye(4))
    centre = rig.camera("cam0").T_rig_camera[:3, 3]
    assert centre[0] == pytest.approx(-BASELINE_M, rel=0.02) and np.hypot(centre[1], centre[2]) < 0.002


def test_held_out_pairs_fall_on_rows_after_rectification():
    folder = data_dir("calib_chessboard_stereo_opencv")

    def images(prefix: str, numbers: list[str]) -> list[tuple[str, np.ndarray | None]]:
        return [(f"{prefix}{n}.jpg", cv2.imread(str(folder / f"{prefix}{n}.jpg"), cv2.IMREAD_GRAYSCALE))
                for n in numbers]

    calibrated, held_out = ["01", "02", "03", "04", "05", "06", "07", "08", "09"], ["11", "12", "13", "14"]
    stereo = calibrate_stereo(images("left", calibrated), images("right", calibrated), BOARD)
    pairs, rejected = find_pairs(images("left", held_out), images("right", held_out), BOARD)
    assert len(pairs) == 4 and rejected == []
    errors = stereo.row_errors_px(pairs)
    assert errors is not None and len(errors) == 4 * 54
    in_sample = stereo.row_errors_px()
    assert in_sample is not None
    held_out_rms, in_sample_rms = np.sqrt(np.mean(errors ** 2)), np.sqrt(np.mean(in_sample ** 2))
    print(f"\nheld-out pairs {held_out_rms:.3f} px RMS on rows after rectification, in-sample {in_sample_rms:.3f} px")
    # half a pixel: what block matching on rectified rows tolerates; and no worse than twice the fitted pairs
    assert held_out_rms < 0.5 and held_out_rms < 2 * in_sample_rms + 0.1
    assert stereo.baseline_m == pytest.approx(BASELINE_M, rel=0.02)
    assert np.degrees(rotation_angle(invert(stereo.T_second_first)[:3, :3], np.eye(3))) < 2.0


UNUSABLE = {
    "no images": (("--stereo", "{empty}", "{empty}", *CHESSBOARD), "no images .* match"),
    "one folder for both": (("--stereo", "{folder}", "{folder}", "--glob", "*.jpg", *CHESSBOARD),
                            "left01.jpg is an image of both cameras"),
    "unequal counts": (("--stereo", "{left}", "{folder}/right0*.jpg", *CHESSBOARD),
                       "13 images of cam0 .* but 9 of cam1 .*: images are paired in name order"),
    "board not found": (("--stereo", "{left}", "{right}", "--pattern", "chessboard", "--size", "7x6", "--square",
                         "0.025"),
                        "camera cam0: the chessboard of 7x6 inner corners was found in none of the 13 images"),
    "one camera": (("--stereo", "{left}", *CHESSBOARD),
                   r"--stereo needs the images of two cameras \(LEFT RIGHT\), got 1"),
    "two globs without --stereo": (("{left}", "{right}", *CHESSBOARD), "one camera takes one DIR_OR_GLOB, got 2"),
    "one name": (("--stereo", "{left}", "{right}", *CHESSBOARD, "--names", "left"),
                 "--names 'left': give two camera names"),
    "unknown rig frame": (("--stereo", "{left}", "{right}", *CHESSBOARD, "--rig-frame", "cam2"),
                          "--rig-frame 'cam2' is none of the cameras"),
    "names without --stereo": (("{left}", *CHESSBOARD, "--names", "a,b"), "--names is for --stereo"),
}
"""Case -> (``artrack calibrate`` options, ``{folder}``, ``{left}``, ``{right}`` (the sample's globs) and ``{empty}``
(an empty folder) filled in; a pattern of the one ERROR line)."""


@pytest.mark.parametrize("case", list(UNUSABLE))
def test_unusable_input_exits_2_with_one_line(procs, tmp_path, case):
    folder = data_dir("calib_chessboard_stereo_opencv")
    empty = tmp_path / "empty"
    empty.mkdir()
    out = tmp_path / "rig.yaml"
    template, reason = UNUSABLE[case]
    options = [option.format(folder=folder, left=folder / "left*.jpg", right=folder / "right*.jpg", empty=empty)
               for option in template]
    proc = procs.run("calibrate", *options, "--out", str(out), timeout=TIMEOUT_S)
    assert proc.poll() == 2, proc.describe()
    errors = [line for line in proc.stderr.splitlines() if "ERROR" in line]
    assert len(errors) == 1 and re.search(reason, errors[0]), proc.stderr
    assert not out.exists()
