"""``artrack calibrate`` on OpenCV's own sample photos, compared with the figures OpenCV gets from them.

The stereo sample (SOURCE.md): calibrateCamera RMS left 0.41 px, right 0.46 px with
findChessboardCorners + cornerSubPix; left fx = fy = 536.0, cx 342.4, cy 235.5. The ChArUco
tutorial photos img_00..03: RMS 0.188 px, fx 457.3, fy 461.3 (OpenCV 5.0, as SOURCE.md reports).
"""

import re

import pytest

from services.calibration.camera_info import read_camera_info
from tests.data import data_dir

pytestmark = pytest.mark.integration

CHESSBOARD = ("--pattern", "chessboard", "--size", "9x6", "--square", "0.025")
TIMEOUT_S = 120.0


def total_rms(stdout: str) -> float:
    found = re.search(r"^(\d+) views, \d+ points: rms ([0-9.]+) px", stdout, re.MULTILINE)
    assert found, stdout
    return float(found.group(2))


def test_left_chessboards_match_opencvs_calibration(procs, tmp_path):
    folder = data_dir("calib_chessboard_stereo_opencv")
    out = tmp_path / "left.yaml"
    proc = procs.run("calibrate", str(folder), "--glob", "left*.jpg", *CHESSBOARD, "--camera", "left",
                     "--out", str(out), timeout=TIMEOUT_S)
    assert proc.poll() == 0, proc.describe()
    per_image = re.findall(r"^left\d\d\.jpg: rms ([0-9.]+) px \(54 points\)$", proc.stdout, re.MULTILINE)
    assert len(per_image) == 13 and all(float(rms) < 0.5 for rms in per_image), proc.stdout
    assert total_rms(proc.stdout) < 0.41
    camera = read_camera_info(out)
    assert (camera.name, camera.width, camera.height) == ("left", 640, 480)
    assert camera.K[0, 0] == pytest.approx(536.0, rel=0.02) and camera.K[1, 1] == pytest.approx(536.0, rel=0.02)
    assert abs(camera.K[0, 2] - 342.4) < 5 and abs(camera.K[1, 2] - 235.5) < 5
    assert camera.dist[0] < -0.2  # the sample lens has strong barrel distortion


def test_a_glob_picks_the_right_camera(procs, tmp_path):
    folder = data_dir("calib_chessboard_stereo_opencv")
    out = tmp_path / "right.yaml"
    proc = procs.run("calibrate", str(folder / "right*.jpg"), *CHESSBOARD, "--out", str(out), timeout=TIMEOUT_S)
    assert proc.poll() == 0, proc.describe()
    assert "left" not in proc.stdout and len(re.findall(r"^right\d\d\.jpg: rms", proc.stdout, re.MULTILINE)) == 13
    assert total_rms(proc.stdout) < 0.46
    camera = read_camera_info(out)
    assert camera.name == "cam0" and 500 < camera.K[0, 0] < 570


def test_charuco_photos_match_opencvs_calibration(procs, tmp_path):
    folder = data_dir("aruco_charuco_opencv_tutorial")
    out = tmp_path / "charuco.yaml"
    proc = procs.run("calibrate", str(folder), "--glob", "img_0*.jpg", "--pattern", "charuco", "--size", "5x7",
                     "--square", "0.04", "--marker", "0.02", "--dictionary", "DICT_6X6_250", "--out", str(out),
                     timeout=TIMEOUT_S)
    assert proc.poll() == 0, proc.describe()
    assert re.search(r"^4 views, 96 points", proc.stdout, re.MULTILINE), proc.stdout
    assert total_rms(proc.stdout) == pytest.approx(0.188, abs=0.03)
    camera = read_camera_info(out)
    assert camera.K[0, 0] == pytest.approx(457.3, rel=0.02) and camera.K[1, 1] == pytest.approx(461.3, rel=0.02)


def test_unusable_sets_exit_2_with_the_reason_and_write_nothing(procs, tmp_path):
    folder = data_dir("calib_chessboard_stereo_opencv")
    out = tmp_path / "camera.yaml"
    cases = [
        (("--glob", "left0[12].jpg", *CHESSBOARD), r"only 2 usable view\(s\); at least 3 are needed"),
        (("--glob", "left*.jpg", "--pattern", "chessboard", "--size", "7x6", "--square", "0.025"),
         "chessboard of 7x6 inner corners was found in none of the 13 images"),
        (("--glob", "nothing*.png", *CHESSBOARD), "no images .* match"),
        (("--glob", "left*.jpg", "--pattern", "charuco", "--size", "5x7", "--square", "0.04"),
         "--pattern charuco needs --marker and --dictionary"),
    ]
    for options, reason in cases:
        proc = procs.run("calibrate", str(folder), *options, "--out", str(out), timeout=TIMEOUT_S)
        assert proc.poll() == 2, proc.describe()
        errors = [line for line in proc.stderr.splitlines() if "ERROR" in line]
        assert len(errors) == 1 and re.search(reason, errors[0]), proc.stderr
        assert not out.exists()


def test_an_output_that_cannot_be_written_or_exists_is_refused_before_calibrating(procs, tmp_path):
    folder = data_dir("calib_chessboard_stereo_opencv")
    existing = tmp_path / "camera.yaml"
    existing.write_text("mine\n")
    for out, reason in ((tmp_path / "nodir" / "x.yaml", f"cannot write {tmp_path / 'nodir' / 'x.yaml'}: folder "
                                                           f"{tmp_path / 'nodir'} does not exist"),
                        (existing, f"{existing} exists: give --force to overwrite it")):
        for mode in ((str(folder), "--glob", "left*.jpg", *CHESSBOARD),
                     ("--wand", str(tmp_path / "wand.mcap"), "--wand-length", "0.5", "--wand-middle", "0.2")):
            proc = procs.run("calibrate", *mode, "--out", str(out), timeout=TIMEOUT_S)
            assert proc.poll() == 2 and "views" not in proc.stdout, proc.describe()  # nothing was calibrated
            errors = [line for line in proc.stderr.splitlines() if line.strip()]
            assert len(errors) == 1 and errors[0].endswith(reason), proc.stderr
    assert existing.read_text() == "mine\n"
    forced = procs.run("calibrate", str(folder), "--glob", "left*.jpg", *CHESSBOARD, "--out", str(existing),
                       "--force", timeout=TIMEOUT_S)
    assert forced.poll() == 0, forced.describe()
    assert read_camera_info(existing).K[0, 0] > 0
