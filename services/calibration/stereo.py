"""Stereo calibration of two cameras from image pairs of one planar target: ``cv2.stereoCalibrateExtended``.

Each camera is first calibrated on its own (``services.calibration.intrinsics``: every image
where it sees the target counts, paired or not). The pose of the second camera relative to the
first then comes from the *pairs*, the images taken at the same moment, where both cameras see
the target: with the intrinsics fixed (``CALIB_FIX_INTRINSIC``), or refined together with it
(``CALIB_USE_INTRINSIC_GUESS``) on request. Only board points seen in both views of a pair are
used (all of a chessboard's; ChArUco corners are matched by their board coordinates).

``T_second_first`` (4, 4) maps first-camera coordinates into the second camera's frame (OpenCV's
``R, T``); its translation's length is the baseline in the unit of the target's square (metres).

A set is refused (``CalibrationError``) when either camera cannot be calibrated, when the two
cameras' image lists differ in length (pairs are matched by position), or when fewer than
``MIN_PAIRS`` = 3 pairs show the target to both cameras: one pair determines the relative pose
but leaves nothing to check it against; from three on, a pair that disagrees shows in its RMS.

Rectification check: ``cv2.stereoRectify`` turns both cameras so that epipolar lines become
image rows; a corner and its match must then lie on the same row. ``row_errors_px`` gives
their row differences, the epipolar error, for the pairs calibrated on or for others
(``find_pairs`` finds them in held-out images).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import cv2
import numpy as np

from services.calibration.intrinsics import Calibration, CalibrationError, Pattern, View, calibrate, find_views
from services.calibration.rig import Rig
from services.geometry.camera import CameraModel
from services.geometry.rotation import matrix_from_rotvec, rotation_angle
from services.geometry.se3 import invert, make_transform

MIN_PAIRS = 3
MIN_COMMON_POINTS = 6
"""Fewest board points a pair's two views must share (a ChArUco view needs as many)."""
CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-10)

Image = tuple[str, np.ndarray | None]
"""A named grey (H, W) uint8 image, None when it could not be read."""


@dataclass(frozen=True)
class Pair:
    """Two views of the target taken together, cut to the board points both see, in one order."""

    name: str
    first: View
    second: View


@dataclass(frozen=True)
class StereoCalibration:
    """Both cameras' calibrations and the pose between them.

    ``T_second_first``: (4, 4), first-camera coordinates into the second camera's frame;
    ``rms_px``: stereo reprojection RMS over both views of every pair; ``pair_rms_px``: (P, 2)
    per pair and camera; ``rejected``: ``(pair name, reason)`` of the pairs not used;
    ``refined``: whether the intrinsics were refined by the stereo fit (then ``first.camera`` and
    ``second.camera`` hold the refined ones, ``first.rms_px`` still the single-camera fit's).
    """

    first: Calibration
    second: Calibration
    T_second_first: np.ndarray
    rms_px: float
    pairs: tuple[Pair, ...]
    pair_rms_px: np.ndarray
    rejected: tuple[tuple[str, str], ...]
    refined: bool

    @property
    def baseline_m(self) -> float:
        """Distance between the two camera centres (the target's unit: metres)."""
        return float(np.linalg.norm(self.T_second_first[:3, 3]))

    @property
    def rotation_deg(self) -> float:
        """Angle of the rotation between the two camera frames."""
        return float(np.degrees(rotation_angle(self.T_second_first[:3, :3], np.eye(3))))

    def rig(self, name: str, frame: str | None = None) -> Rig:
        """The two cameras as a Rig whose frame is camera ``frame``'s (default: the first camera)."""
        first, second = self.first.camera, self.second.camera
        frame = frame or first.name
        if frame == first.name:
            T_rig_first, T_rig_second = np.eye(4), invert(self.T_second_first)
        elif frame == second.name:
            T_rig_first, T_rig_second = self.T_second_first, np.eye(4)
        else:
            raise CalibrationError(f"rig frame {frame!r} is none of the cameras ({first.name}, {second.name})")
        return Rig(name, (replace(first, T_rig_camera=T_rig_first), replace(second, T_rig_camera=T_rig_second)))

    def row_errors_px(self, pairs: Sequence[Pair] | None = None) -> np.ndarray | None:
        """(N,) row differences (px) of the matched points of ``pairs`` (default: those calibrated on)
        after ``cv2.stereoRectify``; None when the two cameras' images differ in size."""
        first, second = self.first.camera, self.second.camera
        if (first.width, first.height) != (second.width, second.height):
            return None
        R, T = self.T_second_first[:3, :3], self.T_second_first[:3, 3:]
        R1, R2, P1, P2, *_ = cv2.stereoRectify(first.K, first.dist, second.K, second.dist,
                                               (first.width, first.height), R, T)
        errors = []
        for pair in self.pairs if pairs is None else pairs:
            rows1 = cv2.undistortPoints(pair.first.image_points.reshape(-1, 1, 2), first.K, first.dist,
                                        R=R1, P=P1).reshape(-1, 2)[:, 1]
            rows2 = cv2.undistortPoints(pair.second.image_points.reshape(-1, 1, 2), second.K, second.dist,
                                        R=R2, P=P2).reshape(-1, 2)[:, 1]
            errors.append(rows1 - rows2)
        return np.concatenate(errors) if errors else np.zeros(0)

    def report(self) -> str:
        """Per-pair RMS, rejected pairs, a table of both cameras and the pose between them, their models."""
        first, second = self.first, self.second
        lines = [f"{pair.name}: rms {a:.3f} / {b:.3f} px ({len(pair.first.image_points)} points)"
                 for pair, (a, b) in zip(self.pairs, self.pair_rms_px, strict=True)]
        lines += [f"{name}: rejected, {reason}" for name, reason in self.rejected]
        t = invert(self.T_second_first)[:3, 3]
        rows = [
            ("camera", first.camera.name, second.camera.name),
            ("views", str(len(first.views)), str(len(second.views))),
            ("rms px", f"{first.rms_px:.3f}", f"{second.rms_px:.3f}"),
            ("pairs used", f"{len(self.pairs)} of {len(self.pairs) + len(self.rejected)}", ""),
            ("stereo rms px", f"{self.rms_px:.3f}",
             "intrinsics refined (one-sigma below: each camera's own fit)" if self.refined else "intrinsics fixed"),
            ("baseline m", f"{self.baseline_m:.4f}",
             f"{second.camera.name} at ({t[0]:.4f}, {t[1]:.4f}, {t[2]:.4f}) in {first.camera.name}"),
            ("rotation deg", f"{self.rotation_deg:.3f}", ""),
        ]
        errors = self.row_errors_px()
        if errors is not None:
            rms, worst = float(np.sqrt(np.mean(errors ** 2))), float(np.abs(errors).max())
            rows.append(("epipolar px", f"{rms:.3f}", f"rms; max {worst:.3f} (rows after stereoRectify)"))
        widths = [max(len(row[i]) for row in rows) for i in range(2)]
        lines += [f"{a:<{widths[0]}}  {b:<{widths[1]}}  {c}".rstrip() for a, b, c in rows]
        for calibration in (first, second):
            lines += [f"{calibration.camera.name}: {line}" for line in calibration.model_lines()]
        return "\n".join(lines)


def match_pair(name: str, first: View, second: View) -> Pair | None:
    """The pair of ``first`` and ``second`` cut to the board points both see, or None if they share too few."""
    index = {tuple(point): i for i, point in enumerate(second.board_points.tolist())}
    matches = [(i, index[tuple(point)]) for i, point in enumerate(first.board_points.tolist())
               if tuple(point) in index]
    if len(matches) < MIN_COMMON_POINTS:
        return None
    i, j = np.array(matches).T
    return Pair(name, View(first.name, first.image_points[i], first.board_points[i]),
                View(second.name, second.image_points[j], second.board_points[j]))


def find_pairs(first_images: Sequence[Image], second_images: Sequence[Image], pattern: Pattern
               ) -> tuple[list[Pair], list[tuple[str, str]]]:
    """The pairs of images taken together (``first_images[i]`` with ``second_images[i]``) where both views show
    ``pattern``, and ``(pair name, reason)`` of the others; for checking a calibration on pairs it did not use."""
    found: tuple[dict[str, View], dict[str, View]] = ({}, {})
    reasons: tuple[dict[str, str], dict[str, str]] = ({}, {})
    for images, views, why in zip((first_images, second_images), found, reasons, strict=True):
        for name, grey in images:
            points = None if grey is None else pattern.find(grey)
            if points is None:
                why[name] = "cannot be read as an image" if grey is None else f"{pattern.describe()} not found"
            else:
                views[name] = View(name, *points)
    names = [(name1, name2) for (name1, _), (name2, _) in zip(first_images, second_images, strict=True)]
    return _pair_views(names, (found[0], reasons[0]), (found[1], reasons[1]))


def _pair_views(names: Sequence[tuple[str, str]], *cameras: tuple[dict[str, View], dict[str, str]]
                ) -> tuple[list[Pair], list[tuple[str, str]]]:
    """Pairs of the image ``names`` whose views both cameras' ``(views by image name, skip reasons)`` hold."""
    (found1, why1), (found2, why2) = cameras
    pairs, rejected = [], []
    for name1, name2 in names:
        pair_name = f"{name1} + {name2}"
        view1, view2 = found1.get(name1), found2.get(name2)
        if view1 is None or view2 is None:
            missing, reasons = (name1, why1) if view1 is None else (name2, why2)
            rejected.append((pair_name, f"{missing}: {reasons.get(missing, 'not used')}"))
            continue
        pair = match_pair(pair_name, view1, view2)
        if pair is None:
            rejected.append((pair_name, f"the two views share fewer than {MIN_COMMON_POINTS} board points"))
            continue
        pairs.append(pair)
    return pairs, rejected


def _intrinsics(images: Sequence[Image], pattern: Pattern, name: str) -> Calibration:
    try:
        views, skipped, size = find_views(images, pattern)
        return calibrate(views, size, name, skipped)
    except CalibrationError as exc:
        raise CalibrationError(f"camera {name}: {exc}") from exc


def calibrate_stereo(first_images: Sequence[Image], second_images: Sequence[Image], pattern: Pattern,
                     names: tuple[str, str] = ("cam0", "cam1"), refine_intrinsics: bool = False
                     ) -> StereoCalibration:
    """Calibrate two cameras and the pose between them from image lists paired by position.

    ``first_images[i]`` and ``second_images[i]`` were taken together. CalibrationError (one line,
    naming the camera) when the lists differ in length, a camera cannot be calibrated, or fewer
    than MIN_PAIRS pairs show the target to both cameras.
    """
    if len(first_images) != len(second_images):
        raise CalibrationError(f"{len(first_images)} images of {names[0]} but {len(second_images)} of {names[1]}: "
                               "images are paired in name order, so each camera needs one image per pair")
    if names[0] == names[1]:
        raise CalibrationError(f"the two cameras need distinct names, got {names[0]!r} twice")
    first, second = _intrinsics(first_images, pattern, names[0]), _intrinsics(second_images, pattern, names[1])
    names_in_order = [(name1, name2) for (name1, _), (name2, _) in zip(first_images, second_images, strict=True)]
    pairs, rejected = _pair_views(names_in_order, *(({view.name: view for view in c.views}, dict(c.skipped))
                                                    for c in (first, second)))
    if len(pairs) < MIN_PAIRS:
        raise CalibrationError(f"only {len(pairs)} pair(s) show the {pattern.describe()} to both cameras; "
                               f"at least {MIN_PAIRS} are needed (10 or more, at varied tilts, are advised)")
    fit = fit_stereo(pairs, first.camera, second.camera, refine_intrinsics)
    if refine_intrinsics:
        first, second = replace(first, camera=fit.first), replace(second, camera=fit.second)
    return StereoCalibration(first=first, second=second, T_second_first=fit.T_second_first, rms_px=fit.rms_px,
                             pairs=tuple(pairs), pair_rms_px=fit.pair_rms_px, rejected=tuple(rejected),
                             refined=refine_intrinsics)


@dataclass(frozen=True)
class StereoFit:
    """``cv2.stereoCalibrateExtended``'s answer: the cameras (refined or as given), ``T_second_first`` (4, 4),
    the RMS over both views of every pair and (P, 2) per pair and camera."""

    first: CameraModel
    second: CameraModel
    T_second_first: np.ndarray
    rms_px: float
    pair_rms_px: np.ndarray


def fit_stereo(pairs: Sequence[Pair], first: CameraModel, second: CameraModel,
               refine_intrinsics: bool = False) -> StereoFit:
    """The pose of camera ``second`` relative to ``first`` from ``pairs``, their intrinsics fixed or refined."""
    flags = cv2.CALIB_USE_INTRINSIC_GUESS if refine_intrinsics else cv2.CALIB_FIX_INTRINSIC
    try:
        rms, K1, d1, K2, d2, R, T, _, _, _, _, per_view = cv2.stereoCalibrateExtended(
            [p.first.board_points for p in pairs], [p.first.image_points for p in pairs],
            [p.second.image_points for p in pairs], first.K.copy(), first.dist.copy(), second.K.copy(),
            second.dist.copy(), (first.width, first.height), None, None,
            flags=flags, criteria=CRITERIA)  # type: ignore[call-overload]  # R and T are outputs: None is accepted
    except cv2.error as exc:
        raise CalibrationError(f"OpenCV could not calibrate the pair of cameras: {exc.err}") from exc
    if not np.all(np.isfinite(T)):
        raise CalibrationError("the stereo calibration did not converge")
    R = np.asarray(R, dtype=np.float64)
    R = R if R.shape == (3, 3) else matrix_from_rotvec(R.ravel())
    return StereoFit(first=replace(first, K=K1, dist=np.asarray(d1, dtype=np.float64).ravel()[:5]),
                     second=replace(second, K=K2, dist=np.asarray(d2, dtype=np.float64).ravel()[:5]),
                     T_second_first=make_transform(R, T), rms_px=float(rms),
                     pair_rms_px=np.asarray(per_view, dtype=np.float64).reshape(-1, 2))
