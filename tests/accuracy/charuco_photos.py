"""OpenCV's ChArUco tutorial photos (``aruco_charuco_opencv_tutorial``, see its SOURCE.md) as pose problems.

The board: 5x7 squares of 0.04 m, markers of 0.02 m, DICT_6X6_250, intrinsics
``tutorial_camera_charuco.yml``. There is no ground truth; a photo's reference pose is the one
its interpolated ChArUco corners give (cv2.solvePnP), which the marker corners only seed.
``photo_poses`` scores the board pose from the marker corners alone, per corner refinement,
against that reference, and compares ``MarkerPoseEstimator``'s board pose with cv2.solvePnP's
on the same corners.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from services.detection.markers.detector import MarkerDetector
from services.estimation.markers.map import MarkerMap, map_from_poses
from services.estimation.markers.pose import MarkerPoseEstimator
from services.geometry.rotation import matrix_from_rotvec, rotation_angle
from services.geometry.se3 import make_transform

DATA_SET = "aruco_charuco_opencv_tutorial"
CHARUCO_PHOTOS = ("choriginal.jpg", "img_00.jpg", "img_01.jpg", "img_02.jpg", "img_03.jpg")
OCCLUDED_PHOTO = "chocclusion_original.jpg"
CALIBRATION = "tutorial_camera_charuco.yml"
DICTIONARY = "DICT_6X6_250"
SQUARES = (5, 7)
SQUARE_M, MARKER_M = 0.04, 0.02
BOARD_FLIP = np.diag([1.0, -1.0, -1.0])
"""Rotation from a marker frame (x right, y up, z out of the board) into the board frame OpenCV
gives ChArUco object points in (x right, y down, z into the board)."""


def intrinsics(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """``(K (3, 3), dist (N,))`` of an OpenCV calibration YAML."""
    storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    try:
        return storage.getNode("camera_matrix").mat(), storage.getNode("distortion_coefficients").mat().ravel()
    finally:
        storage.release()


def reprojection_rms(board_points: np.ndarray, image_points: np.ndarray, K: np.ndarray,
                     dist: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """``(RMS px, rvec, tvec)`` of the cv2.solvePnP pose of (N, 3) board points seen at (N, 2) pixels."""
    board_points, image_points = board_points.reshape(-1, 3), image_points.reshape(-1, 2)
    ok, rvec, tvec = cv2.solvePnP(board_points, image_points, K, dist)
    assert ok
    projected, _ = cv2.projectPoints(board_points, rvec, tvec, K, dist)
    return float(np.sqrt(np.mean(np.sum((projected.reshape(-1, 2) - image_points) ** 2, axis=1)))), rvec, tvec


def charuco(refinement: str = "lines") -> tuple[MarkerDetector, cv2.aruco.CharucoBoard]:
    """The photos' detector (with ``refinement``) and board."""
    detector = MarkerDetector(DICTIONARY, refinement=refinement)
    return detector, cv2.aruco.CharucoBoard(SQUARES, SQUARE_M, MARKER_M, detector.dictionary)


def board_map(board: cv2.aruco.CharucoBoard) -> MarkerMap:
    """The board's markers as a MarkerMap whose frame is the board's (OpenCV's object point frame)."""
    poses = {int(i): make_transform(BOARD_FLIP, np.mean(corners, axis=0))
             for i, corners in zip(np.ravel(board.getIds()), board.getObjPoints(), strict=True)}
    return map_from_poses("charuco", poses, MARKER_M)


def transform(rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    """(4, 4) of an OpenCV rotation vector and translation."""
    return make_transform(matrix_from_rotvec(np.ravel(rvec)), np.ravel(tvec))


def pose_difference(T: np.ndarray, T_ref: np.ndarray) -> tuple[float, float, float]:
    """Rotation difference (deg), translation difference (mm) and signed range difference
    (% of the reference distance, positive = ``T`` farther) of (4, 4) ``T`` from ``T_ref``."""
    distance = np.linalg.norm(T_ref[:3, 3])
    return (float(np.degrees(rotation_angle(T[:3, :3], T_ref[:3, :3]))),
            float(1e3 * np.linalg.norm(T[:3, 3] - T_ref[:3, 3])),
            float(100 * (np.linalg.norm(T[:3, 3]) - distance) / distance))


def photo_poses(folder: Path, name: str, refinement: str, calibrated: bool = True) -> dict[str, float]:
    """One photo's figures with ``refinement`` (``lines`` given the calibration when ``calibrated``):
    the marker corners' board pose (cv2.solvePnP) and its reprojection RMS, its difference from the
    ChArUco reference pose, and the difference between ``MarkerPoseEstimator``'s board pose and
    cv2.solvePnP's on the same marker corners."""
    detector, board = charuco(refinement)
    K, dist = intrinsics(folder / CALIBRATION)
    image = cv2.imread(str(folder / name))
    found = detector.detect(image, K, dist) if calibrated else detector.detect(image)
    corners, corner_ids, _, _ = cv2.aruco.CharucoDetector(board).detectBoard(
        image, markerCorners=list(found.corners), markerIds=found.ids)
    charuco_rms, rvec, tvec = reprojection_rms(*board.matchImagePoints(corners, corner_ids), K, dist)
    markers_only = cv2.aruco.Board(board.getObjPoints(), board.getDictionary(), board.getIds())
    marker_rms, rvec_m, tvec_m = reprojection_rms(*markers_only.matchImagePoints(list(found.corners), found.ids),
                                                  K, dist)
    T_ref, T_opencv = transform(rvec, tvec), transform(rvec_m, tvec_m)
    estimate = MarkerPoseEstimator(marker_map=board_map(board)).estimate(found.ids, found.corners, 0.0, K, dist)
    ours = next(pose for pose in estimate.poses if pose.target == "charuco")
    vs_ref = pose_difference(T_opencv, T_ref)
    vs_opencv = pose_difference(ours.T, T_opencv)
    return {"markers": len(found), "charuco_corners": int(len(corner_ids)), "charuco_rms_px": charuco_rms,
            "marker_rms_px": marker_rms, "rotation_vs_charuco_deg": vs_ref[0],
            "translation_vs_charuco_mm": vs_ref[1], "range_vs_charuco_pct": vs_ref[2],
            "ours_rms_px": ours.rms_px, "ours_vs_opencv_rotation_deg": vs_opencv[0],
            "ours_vs_opencv_translation_mm": vs_opencv[1], "distance_m": float(np.linalg.norm(T_ref[:3, 3]))}
