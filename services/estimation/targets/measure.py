"""Sub-pixel measurement of target points in a frame against the target itself, and the homography refit on them.

Keypoints place a target's points to about a pixel of their pyramid level; a homography ``H`` (3, 3),
target-image pixel (level 0) -> undistorted frame pixel, fitted to them inherits that. Measuring the
points against the target image does better, because the target's own pixels say exactly where each
point is:

1. The target is drawn at ``H`` (``TargetAligner.view``: a warp of the pyramid level whose pixels are
   nearest the frame's) amid the frame's own pixels, so the coarse levels of the search see the same
   surroundings, its gain and offset matched to the frame's over the target (mean and standard
   deviation), so a print's contrast need not match the camera's.
2. Each point is followed by pyramidal Lucas-Kanade (``cv2.calcOpticalFlowPyrLK``) from where ``H``
   puts it in the drawing to the frame, starting there too, then back from the frame to the drawing;
   it is kept only when found both ways and back within ``forward_backward_px`` of where it started.

Where ``H`` was right a point stays put; where it was off, the point moves to where the frame shows it.
Tracking anchors its points this way (``services.estimation.targets.tracking``), and recognition refits
its homography and pose on the points so measured (``refine_homography``).

Pixels put the centre of the top-left pixel at (0, 0); frames are (H, W) uint8 and undistorted
(``geometry.camera.undistort_image`` onto the same ``K`` first when the lens distorts).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator

from services.estimation.targets.alignment import TargetAligner

__all__ = ["MeasureOptions", "Refinement", "follow", "measure_points", "refine_homography"]

LK_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.01)
MIN_STD = 1e-6


class MeasureOptions(BaseModel):
    """The Lucas-Kanade settings of following and measuring points."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    window_px: int = Field(default=13, ge=5, description="side of the Lucas-Kanade window (odd), px")
    levels: int = Field(default=3, ge=0, le=8, description="pyramid levels above the frame's own (coarse to fine; "
                                                           "each doubles the reach)")
    forward_backward_px: float = Field(default=0.5, gt=0, description="largest distance between a point and where "
                                                                      "following it forward and back brings it, px")

    @field_validator("window_px")
    @classmethod
    def _odd(cls, window_px: int) -> int:
        if window_px % 2 == 0:
            raise ValueError(f"window_px must be odd, got {window_px}")
        return window_px


@dataclass(frozen=True)
class Refinement:
    """``homography`` (3, 3) target-image pixel -> undistorted frame pixel, least squares on the kept points;
    ``pixels`` (M, 2) float64 undistorted frame pixels measured of the M points asked for (zero where not
    measured); ``kept`` (M,) bool, measured and within the refit's threshold."""

    homography: np.ndarray
    pixels: np.ndarray
    kept: np.ndarray


def follow(before: np.ndarray, after: np.ndarray, pixels: np.ndarray, guesses: np.ndarray,
           options: MeasureOptions) -> tuple[np.ndarray, np.ndarray]:
    """``(moved, kept)``: (M, 2) float32 pixels in the (H, W) uint8 image ``after`` of the (M, 2) float32
    ``pixels`` of ``before``, searched from (M, 2) ``guesses``, and (M,) bool, found, found back from
    ``after`` and back within ``forward_backward_px`` of ``pixels``."""
    side = (options.window_px, options.window_px)
    if not len(pixels):
        return np.zeros((0, 2), np.float32), np.zeros(0, bool)
    moved, found, _ = cv2.calcOpticalFlowPyrLK(before, after, pixels, guesses.copy(), None, None, side,
                                               options.levels, LK_CRITERIA, cv2.OPTFLOW_USE_INITIAL_FLOW)
    back, returned, _ = cv2.calcOpticalFlowPyrLK(after, before, moved, pixels.copy(), None, None, side,
                                                 options.levels, LK_CRITERIA, cv2.OPTFLOW_USE_INITIAL_FLOW)
    moved = moved.reshape(-1, 2)
    close = np.sum((back.reshape(-1, 2) - pixels) ** 2, axis=1) < options.forward_backward_px**2
    return moved, (found.ravel() == 1) & (returned.ravel() == 1) & close


def measure_points(aligner: TargetAligner, frame: np.ndarray, H: np.ndarray, target_pixels: np.ndarray,
                   options: MeasureOptions) -> tuple[np.ndarray, np.ndarray]:
    """``(pixels, kept)``: (M, 2) float32 undistorted pixels in the (H, W) uint8 undistorted ``frame`` of the
    (M, 2) level-0 ``target_pixels`` of ``aligner``'s target, measured against the target drawn at the (3, 3)
    homography ``H`` (target-image pixel -> undistorted frame pixel), and (M,) bool, those measured (see the
    module's docstring). None is kept when the target is behind the camera or outside the frame."""
    count = len(target_pixels)
    start = cv2.perspectiveTransform(np.asarray(target_pixels, np.float64).reshape(-1, 1, 2), H)
    start = start.reshape(-1, 2).astype(np.float32)
    view = aligner.view(H, frame.shape) if count else None
    if view is None or not view[1].any():
        return start, np.zeros(count, bool)
    drawn, mask = view
    drawn_mean, drawn_std = cv2.meanStdDev(drawn, mask=mask)
    frame_mean, frame_std = cv2.meanStdDev(frame, mask=mask)
    gain = float(frame_std[0, 0]) / max(float(drawn_std[0, 0]), MIN_STD)
    matched = cv2.convertScaleAbs(drawn, alpha=gain, beta=float(frame_mean[0, 0] - gain * drawn_mean[0, 0]))
    matched = np.where(mask > 0, matched, frame)
    return follow(matched, frame, start, start, options)


def refine_homography(aligner: TargetAligner, frame: np.ndarray, H: np.ndarray, target_pixels: np.ndarray,
                      options: MeasureOptions, threshold_px: float, max_points: int,
                      min_points: int = 4) -> Refinement | None:
    """``H`` (3, 3) refitted to the (M, 2) level-0 ``target_pixels`` measured in the (H, W) uint8 undistorted
    ``frame`` (``measure_points``): at most ``max_points`` of them, evenly through their order, are measured;
    USAC_MAGSAC with ``threshold_px`` drops what the measurement got wrong, then least squares on the rest.
    None with fewer than ``min_points`` (at least 4) points kept."""
    target_pixels = np.asarray(target_pixels, np.float64).reshape(-1, 2)
    least = max(min_points, 4)
    chosen = np.arange(0, len(target_pixels), max(math.ceil(len(target_pixels) / max_points), 1))
    pixels, measured = measure_points(aligner, frame, H, target_pixels[chosen], options)
    rows = np.flatnonzero(measured)
    if len(rows) < least:
        return None
    source, destination = target_pixels[chosen[rows]], pixels[rows].astype(np.float64)
    robust, inliers = cv2.findHomography(source, destination, cv2.USAC_MAGSAC, threshold_px)
    if robust is None or inliers is None or int(inliers.sum()) < least:
        return None
    rows = rows[inliers.ravel() > 0]
    refit, _ = cv2.findHomography(target_pixels[chosen[rows]], pixels[rows].astype(np.float64), 0)
    if refit is None:
        return None
    measured_pixels = np.zeros((len(target_pixels), 2))
    measured_pixels[chosen] = pixels
    kept = np.zeros(len(target_pixels), bool)
    kept[chosen[rows]] = True
    return Refinement(refit, measured_pixels, kept)
