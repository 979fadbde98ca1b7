"""Board poses on OpenCV's ChArUco tutorial photos (see tests/accuracy/charuco_photos.py): the corner
refinements compared, and MarkerPoseEstimator against OpenCV on the same corners.

No ground-truth poses exist, so:

* refinements are compared by how well one board pose explains all the marker corners
  (cv2.solvePnP with the calibration's distortion, reprojection RMS; the detector is given the
  calibration): the ``lines`` corners must fit better than OpenCV's ``subpix`` on every photo,
  by at least 10 % on each and 30 % on average;
* ``MarkerPoseEstimator`` with the board as a marker map must give the pose cv2.solvePnP gives
  on the same corners, within ``MAX_ROTATION_GAP_DEG`` and ``MAX_TRANSLATION_GAP_MM``, and the
  same reprojection RMS within 5 % (it undistorts the corners and minimises in undistorted
  pixels, OpenCV in distorted ones, so the optima differ slightly).

``python -m tests.accuracy.report`` prints the figures (``photo_board_pose`` lines).
"""

import numpy as np
import pytest

from services.detection.markers.detector import MarkerDetector
from services.estimation.markers.map import marker_corners
from services.geometry.se3 import transform_points
from tests.accuracy.charuco_photos import (
    CHARUCO_PHOTOS,
    DATA_SET,
    MARKER_M,
    OCCLUDED_PHOTO,
    board_map,
    charuco,
    photo_poses,
)
from tests.data import data_dir

pytestmark = pytest.mark.slow

PHOTOS = (*CHARUCO_PHOTOS, OCCLUDED_PHOTO)
MAX_ROTATION_GAP_DEG = 0.02
MAX_TRANSLATION_GAP_MM = 0.05


@pytest.fixture(scope="module")
def figures():
    folder = data_dir(DATA_SET)
    return {(name, refinement): photo_poses(folder, name, refinement)
            for name in PHOTOS for refinement in ("lines", "subpix")}


def test_the_board_map_holds_the_boards_marker_corners():
    _, board = charuco()
    markers = board_map(board).markers
    assert sorted(markers) == [int(i) for i in np.ravel(board.getIds())]
    for marker_id, corners in zip(np.ravel(board.getIds()), board.getObjPoints(), strict=True):
        placed = transform_points(markers[int(marker_id)].T_map_marker, marker_corners(MARKER_M))
        assert np.allclose(placed, corners, atol=1e-9)


@pytest.mark.parametrize("name", PHOTOS)
def test_marker_pose_estimator_gives_opencvs_board_pose(figures, name):
    for refinement in ("lines", "subpix"):
        found = figures[name, refinement]
        assert found["ours_vs_opencv_rotation_deg"] < MAX_ROTATION_GAP_DEG
        assert found["ours_vs_opencv_translation_mm"] < MAX_TRANSLATION_GAP_MM
        assert found["ours_rms_px"] == pytest.approx(found["marker_rms_px"], rel=0.05)


def test_line_corners_fit_the_board_better_than_subpix(figures):
    ratios = [figures[name, "lines"]["marker_rms_px"] / figures[name, "subpix"]["marker_rms_px"] for name in PHOTOS]
    assert max(ratios) < 0.9 and np.mean(ratios) < 0.7
    assert all(figures[name, "lines"]["markers"] == figures[name, "subpix"]["markers"] for name in PHOTOS)


def test_lines_is_the_default():
    assert MarkerDetector("DICT_6X6_250").refinement == "lines"
