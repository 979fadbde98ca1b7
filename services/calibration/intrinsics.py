"""Intrinsic calibration of one camera from photos of a planar target: Zhang's method, ``cv2.calibrateCamera``.

Targets, each with its board frame (z = 0 on the board, metres):

* ``Chessboard(columns, rows, square_m)``: ``columns x rows`` *inner* corners, found by
  ``cv2.findChessboardCornersSB`` (CALIB_CB_NORMALIZE_IMAGE | CALIB_CB_ACCURACY), which
  locates them to a fraction of a pixel itself. Origin at the first corner OpenCV reports,
  x along a row of corners, y from row to row.
* ``Charuco(columns, rows, square_m, marker_m, dictionary)``: ``columns x rows`` *squares*,
  found by ``cv2.aruco.CharucoDetector.detectBoard``; ``Board.matchImagePoints`` gives each
  interpolated corner's board point (OpenCV's ChArUco frame: origin at the board's top-left
  corner, x right, y down). A view needs ``MIN_CHARUCO_CORNERS`` corners, not all on one line.

Camera model: fx, fy, cx, cy, no skew, plumb_bob distortion (k1, k2, p1, p2, k3), which is
what ``calibrateCamera`` fits with no flags and what the ROS camera_info files hold.

A set of views is refused (``CalibrationError``) when it cannot constrain the intrinsics:

* the target was found in none of the images (the wrong ``--size`` is the usual cause);
* fewer than ``MIN_VIEWS`` = 3 views. Zhang's closed form needs three views of the plane for a
  general camera (two with zero skew, but then nothing is left over for the five distortion
  coefficients); OpenCV's documentation advises ten or more, and more is better;
* all board planes (nearly) parallel: Zhang's degenerate configuration. Views that only move
  the board or turn it in its own plane (fronto-parallel views among them) share one
  vanishing line and add no constraint on the focal length beyond the first. Each view's
  board normal is taken from its vanishing line ``l`` (third row of ``H^-1``, ``H`` the
  board-to-pixel homography) through a nominal camera ``K0`` (f = max(W, H), i.e. a 53 deg
  lens, principal point at the image centre): ``n = normalise(K0^T l)``. Parallel planes
  give the same ``n`` whatever ``K0`` is, so the measure does not depend on the calibration
  it guards. The *tilt spread*, the largest angle between two views' normals, must reach
  ``MIN_TILT_SPREAD_DEG`` = 3 deg: above what (nearly) parallel sets give, below the spread
  of a weak but usable set (the spreads of sample sets are in docs/benchmarks.md).
"""

from __future__ import annotations

import itertools
from collections.abc import Iterable
from dataclasses import dataclass, field

import cv2
import numpy as np

from services.detection.markers.detector import aruco_dictionary
from services.geometry.camera import CameraModel
from services.geometry.homography import DegenerateError, homography_dlt
from services.geometry.rotation import matrix_from_rotvec
from services.geometry.se3 import make_transform

MIN_VIEWS = 3
MIN_TILT_SPREAD_DEG = 3.0
MIN_CHARUCO_CORNERS = 6
CHESSBOARD_FLAGS = cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_ACCURACY


class CalibrationError(ValueError):
    """The images cannot calibrate the camera; the message says why."""


@dataclass(frozen=True)
class Chessboard:
    """A chessboard of ``columns x rows`` inner corners, squares of ``square_m`` metres."""

    columns: int
    rows: int
    square_m: float

    def __post_init__(self) -> None:
        if self.columns < 2 or self.rows < 2 or not self.square_m > 0:
            raise ValueError(f"a chessboard needs at least 2x2 inner corners and a square > 0 m, "
                             f"got {self.columns}x{self.rows}, {self.square_m} m")

    def describe(self) -> str:
        return f"chessboard of {self.columns}x{self.rows} inner corners"

    def find(self, grey: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """``(image_points (N, 2) float32 px, board_points (N, 3) float32 m)`` in ``grey``, or None."""
        found, corners = cv2.findChessboardCornersSB(grey, (self.columns, self.rows), flags=CHESSBOARD_FLAGS)
        if not found:
            return None
        board = np.zeros((self.columns * self.rows, 3), np.float32)
        board[:, :2] = np.mgrid[0:self.columns, 0:self.rows].T.reshape(-1, 2) * self.square_m
        return corners.reshape(-1, 2).astype(np.float32), board


@dataclass(frozen=True)
class Charuco:
    """A ChArUco board of ``columns x rows`` squares (``square_m``), markers of ``marker_m``, ``dictionary``."""

    columns: int
    rows: int
    square_m: float
    marker_m: float
    dictionary: str
    _board: cv2.aruco.CharucoBoard = field(init=False, repr=False, compare=False)
    _detector: cv2.aruco.CharucoDetector = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if self.columns < 2 or self.rows < 2 or not 0 < self.marker_m < self.square_m:
            raise ValueError(f"a ChArUco board needs at least 2x2 squares and 0 < marker < square, "
                             f"got {self.columns}x{self.rows}, square {self.square_m} m, marker {self.marker_m} m")
        board = cv2.aruco.CharucoBoard((self.columns, self.rows), self.square_m, self.marker_m,
                                       aruco_dictionary(self.dictionary))
        object.__setattr__(self, "_board", board)
        object.__setattr__(self, "_detector", cv2.aruco.CharucoDetector(board))

    def describe(self) -> str:
        return f"ChArUco board of {self.columns}x{self.rows} squares ({self.dictionary})"

    def find(self, grey: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """``(image_points (N, 2) float32 px, board_points (N, 3) float32 m)`` in ``grey``, or None."""
        corners, ids, _, _ = self._detector.detectBoard(grey)
        if ids is None or len(ids) < MIN_CHARUCO_CORNERS or self._board.checkCharucoCornersCollinear(ids):
            return None
        board, image = self._board.matchImagePoints(corners, ids)  # type: ignore[call-overload]  # an (N, 1, 2) array
        return image.reshape(-1, 2).astype(np.float32), board.reshape(-1, 3).astype(np.float32)


Pattern = Chessboard | Charuco


@dataclass(frozen=True)
class View:
    """One image where the target was found: ``image_points`` (N, 2) float32 px, ``board_points`` (N, 3) float32 m."""

    name: str
    image_points: np.ndarray
    board_points: np.ndarray


@dataclass(frozen=True)
class Calibration:
    """The result: ``camera`` (K, distortion), the views used and how well the model fits them.

    ``rms_px``: reprojection RMS over every point of every view; ``view_rms_px``: (V,) per view;
    ``T_camera_board``: (V, 4, 4) the board's pose in each view; ``std_px``: (4,) one-sigma
    uncertainty of fx, fy, cx, cy (calibrateCameraExtended); ``tilt_spread_deg``: see the module
    docstring; ``skipped``: ``(image name, reason)`` of the images not used.
    """

    camera: CameraModel
    rms_px: float
    views: tuple[View, ...]
    view_rms_px: np.ndarray
    T_camera_board: np.ndarray
    std_px: np.ndarray
    tilt_spread_deg: float
    skipped: tuple[tuple[str, str], ...] = ()

    def report(self) -> str:
        """Per-image RMS, skipped images, total RMS, K and distortion, as lines of text."""
        lines = [f"{view.name}: rms {rms:.3f} px ({len(view.image_points)} points)"
                 for view, rms in zip(self.views, self.view_rms_px, strict=True)]
        lines += [f"{name}: skipped, {reason}" for name, reason in self.skipped]
        points = sum(len(view.image_points) for view in self.views)
        lines += [
            f"{len(self.views)} views, {points} points: rms {self.rms_px:.3f} px; "
            f"board tilt spread {self.tilt_spread_deg:.1f} deg",
            *self.model_lines(),
        ]
        return "\n".join(lines)

    def model_lines(self) -> list[str]:
        """Image size, K with the one-sigma of fx, fy, cx, cy, and the distortion, as lines of text."""
        K, dist = self.camera.K, self.camera.dist
        sx, sy, scx, scy = self.std_px
        return [
            f"image {self.camera.width}x{self.camera.height}",
            f"K = [[{K[0, 0]:.3f}, 0, {K[0, 2]:.3f}], [0, {K[1, 1]:.3f}, {K[1, 2]:.3f}], [0, 0, 1]]",
            f"one-sigma: fx {sx:.2f}, fy {sy:.2f}, cx {scx:.2f}, cy {scy:.2f} px",
            "distortion (k1, k2, p1, p2, k3) = [" + ", ".join(f"{v:.6f}" for v in dist) + "]",
        ]


def find_views(images: Iterable[tuple[str, np.ndarray | None]], pattern: Pattern
               ) -> tuple[list[View], list[tuple[str, str]], tuple[int, int]]:
    """The views where ``pattern`` is found among ``(name, grey (H, W) uint8 or None if unreadable)`` images.

    Returns the views, ``(name, reason)`` of the images skipped, and the image size ``(W, H)``
    (that of the first readable image; images of another size are skipped). Raises
    CalibrationError when no image is readable or the pattern is found in none.
    """
    views, skipped, size, readable = [], [], None, 0
    for name, grey in images:
        if grey is None:
            skipped.append((name, "cannot be read as an image"))
            continue
        readable += 1
        shape = (grey.shape[1], grey.shape[0])
        size = size or shape
        if shape != size:
            skipped.append((name, f"size {shape[0]}x{shape[1]} differs from the first image's {size[0]}x{size[1]}"))
            continue
        found = pattern.find(grey)
        if found is None:
            skipped.append((name, f"{pattern.describe()} not found"))
            continue
        views.append(View(name, *found))
    if size is None:
        raise CalibrationError("none of the images could be read")
    if not views:
        raise CalibrationError(f"the {pattern.describe()} was found in none of the {readable} images: "
                               "check the pattern size (inner corners for a chessboard, squares for ChArUco)")
    return views, skipped, size


def board_normals(views: Iterable[View], image_size: tuple[int, int]) -> np.ndarray:
    """(V, 3) unit board normals through the nominal camera K0 of the module docstring, sign z < 0 (facing it)."""
    width, height = image_size
    f = float(max(width, height))
    K0 = np.array([[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0.0, 0.0, 1.0]])
    normals = []
    for view in views:
        try:
            H = homography_dlt(view.board_points[:, :2], view.image_points)
        except DegenerateError as exc:
            raise CalibrationError(f"{view.name}: the target's points do not span the board ({exc})") from exc
        n = K0.T @ np.linalg.inv(H)[2]
        n /= np.linalg.norm(n)
        normals.append(-n if n[2] > 0 else n)
    return np.array(normals)


def tilt_spread_deg(normals: np.ndarray) -> float:
    """Largest angle (deg) between two of the (V, 3) unit normals; 0 for fewer than two."""
    angles = [np.degrees(np.arccos(np.clip(a @ b, -1.0, 1.0))) for a, b in itertools.combinations(normals, 2)]
    return float(max(angles, default=0.0))


def calibrate(views: list[View], image_size: tuple[int, int], name: str = "cam0",
              skipped: Iterable[tuple[str, str]] = ()) -> Calibration:
    """Calibrate from ``views`` of images ``image_size`` = (W, H); CalibrationError when they cannot constrain it."""
    skipped = tuple(skipped)
    if len(views) < MIN_VIEWS:
        unused = f" (skipped: {', '.join(image for image, _ in skipped)})" if skipped else ""
        raise CalibrationError(f"only {len(views)} usable view(s){unused}; at least {MIN_VIEWS} are needed "
                               "(10 or more, at varied tilts, are advised)")
    spread = tilt_spread_deg(board_normals(views, image_size))
    if spread < MIN_TILT_SPREAD_DEG:
        raise CalibrationError(f"the board planes of all {len(views)} views are nearly parallel (tilt spread "
                               f"{spread:.1f} deg < {MIN_TILT_SPREAD_DEG:.0f} deg): the focal length is not "
                               "determined; add views with the board tilted by 20 to 45 deg in different directions")
    try:
        rms, K, dist, rvecs, tvecs, std_intrinsics, _, per_view = cv2.calibrateCameraExtended(
            [v.board_points for v in views], [v.image_points for v in views], image_size,
            None, None)  # type: ignore[call-overload]  # K and dist are outputs: None is accepted
    except cv2.error as exc:
        raise CalibrationError(f"OpenCV could not calibrate from these views: {exc.err}") from exc
    width, height = image_size
    if not (np.all(np.isfinite(K)) and K[0, 0] > 0 and K[1, 1] > 0
            and 0 <= K[0, 2] <= width - 1 and 0 <= K[1, 2] <= height - 1):
        raise CalibrationError(f"the calibration did not converge to a plausible camera (K = {K.round(1).tolist()})")
    camera = CameraModel(name, width, height, K, np.asarray(dist, dtype=np.float64).ravel()[:5], np.eye(4))
    poses = np.array([make_transform(matrix_from_rotvec(r), t) for r, t in zip(rvecs, tvecs, strict=True)])
    return Calibration(camera=camera, rms_px=float(rms), views=tuple(views),
                       view_rms_px=np.asarray(per_view, dtype=np.float64).ravel(), T_camera_board=poses,
                       std_px=np.asarray(std_intrinsics, dtype=np.float64).ravel()[:4], tilt_spread_deg=spread,
                       skipped=skipped)


def calibrate_images(images: Iterable[tuple[str, np.ndarray | None]], pattern: Pattern,
                     name: str = "cam0") -> Calibration:
    """``find_views`` then ``calibrate``: the camera ``name`` from named grey images (None = unreadable)."""
    views, skipped, size = find_views(images, pattern)
    return calibrate(views, size, name, skipped)
