"""Sub-pixel refinement of a target's pose by direct alignment of the target image with the frame.

Keypoints and tracked points place the target to a fraction of a pixel at best; aligning the whole
image does better, because every textured pixel of the visible target takes part. From a pose
``T_camera_target`` (4, 4) the homography target-image pixel -> undistorted frame pixel is
``H = K [r1 r2 t] S`` (``S``: ``Target.plane_from_pixel``). OpenCV's enhanced correlation coefficient
maximisation (``cv2.findTransformECC``, ``MOTION_HOMOGRAPHY``; Evangelidis and Psarakis, 2008) refines
``H`` against the frame: it is invariant to a change of gain and offset between target and frame, so
the printed image's contrast need not match the camera's. The refined ``H`` maps a grid of target
pixels into the frame, and the pose of those correspondences (``services.estimation.targets.pose``)
is the refined pose.

The template is the level of the target image's pyramid (``cv2.pyrDown``, which maps pixel
coordinates exactly by 1/2 per level) whose pixels are closest to, but not larger than, the frame's
pixels at the target's centre, so the alignment neither aliases nor wastes time on detail the frame
cannot show. Only frame pixels inside the target's outline, ``margin_px`` in from it, take part. A
distorted frame is undistorted first (``geometry.camera.undistort_image``, onto the same ``K``).

The refinement is refused (None) when ECC fails, its correlation is below ``min_correlation``, or it
moves a point of the visible target by more than ``max_shift_px`` (it has left the basin it started in).
"""

from __future__ import annotations

import math

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator

from services.estimation.targets.pose import fit_planar_pose
from services.estimation.targets.target import Target, target_points
from services.geometry.camera import plane_homography, undistort_image

__all__ = ["AlignmentOptions", "TargetAligner"]

GRID = 8
"""Target pixels per side of the grid the refined homography maps into the frame for the pose."""
MIN_LEVEL_SIDE = 32


class AlignmentOptions(BaseModel):
    """ECC's stopping test and what of the target and the frame it compares."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    iterations: int = Field(default=30, ge=1, description="ECC's iterations at most")
    epsilon: float = Field(default=1e-5, gt=0, description="ECC stops once the correlation gains less than this")
    smoothing: int = Field(default=3, ge=1, description="side of the gaussian ECC blurs both images with (odd), px; "
                                                        "1: none")
    margin_px: float = Field(default=4.0, ge=0, description="frame pixels this far inside the target's outline "
                                                            "are left out")
    min_correlation: float = Field(default=0.6, ge=-1, le=1, description="least correlation of an accepted "
                                                                         "alignment")
    max_shift_px: float = Field(default=4.0, gt=0, description="largest move of a visible target point (of an 8 x 8 "
                                                               "grid) an alignment may make, px")

    @field_validator("smoothing")
    @classmethod
    def _odd(cls, smoothing: int) -> int:
        if smoothing % 2 == 0:
            raise ValueError(f"smoothing must be odd, got {smoothing}")
        return smoothing


class TargetAligner:
    """Refines poses of one target; holds the target image's pyramid."""

    def __init__(self, target: Target, options: AlignmentOptions | None = None):
        self.target = target
        self.options = options or AlignmentOptions()
        self.levels = [target.image]
        while min(self.levels[-1].shape) >= 2 * MIN_LEVEL_SIDE:
            self.levels.append(cv2.pyrDown(self.levels[-1]))
        w, h = target.size_px
        u, v = np.meshgrid(np.linspace(0, w - 1, GRID), np.linspace(0, h - 1, GRID))
        self.grid = np.stack([u.ravel(), v.ravel()], axis=1)
        self.grid_points = target_points(self.grid, target.size_px, target.width_m)
        self.criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, self.options.iterations,
                         self.options.epsilon)

    def homography(self, K: np.ndarray, T_camera_target: np.ndarray) -> np.ndarray:
        """(3, 3) target-image pixel (level 0) -> undistorted frame pixel of the pose ``T_camera_target``."""
        return plane_homography(K, T_camera_target) @ self.target.plane_from_pixel()

    def level(self, H: np.ndarray) -> int:
        """The pyramid level whose pixels, mapped by ``H`` at the target's centre, are nearest one frame
        pixel without being larger."""
        w, h = self.target.size_px
        centre = np.array([[(w - 1) / 2, (h - 1) / 2], [(w + 1) / 2, (h - 1) / 2], [(w - 1) / 2, (h + 1) / 2]])
        mapped = cv2.perspectiveTransform(centre.reshape(-1, 1, 2), H).reshape(3, 2)
        (a, b), (c, d) = mapped[1] - mapped[0], mapped[2] - mapped[0]
        area = abs(float(a * d - b * c))
        texels_per_pixel = 1.0 / math.sqrt(max(area, 1e-12))
        return int(np.clip(math.floor(math.log2(max(texels_per_pixel, 1.0))), 0, len(self.levels) - 1))

    def view(self, H: np.ndarray, shape: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray] | None:
        """``(image, mask)``: the target as the (3, 3) homography ``H`` (target-image pixel, level 0 ->
        undistorted frame pixel) draws it, from the pyramid level ``level`` picks, and where it covers the
        frame ``margin_px`` in from its outline; both (H, W) uint8 for a frame of ``shape`` (H, W). None when
        the target is behind the camera."""
        k = self.level(H)
        outline = self._outline(H)
        if outline is None:
            return None
        image = cv2.warpPerspective(self.levels[k], H @ np.diag([2.0**k, 2.0**k, 1.0]), (shape[1], shape[0]),
                                    flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        return image, self._mask(outline, shape)

    def refine(self, grey: np.ndarray, K: np.ndarray, dist: np.ndarray | None,
               T_camera_target: np.ndarray) -> np.ndarray | None:
        """The refined (4, 4) ``T_camera_target`` of the target in the (H, W) uint8 frame ``grey`` seen by
        ``K`` (3, 3) with OpenCV distortion ``dist`` (None: none), starting from ``T_camera_target``;
        None when refused (see the module's docstring)."""
        o = self.options
        frame = grey if dist is None else undistort_image(grey, K, dist)
        H = self.homography(K, T_camera_target)
        k = self.level(H)
        scale = np.diag([2.0**k, 2.0**k, 1.0])
        outline = self._outline(H)
        if outline is None:
            return None
        mask = self._mask(outline, frame.shape)
        if not mask.any():
            return None
        warp = H @ scale
        try:
            correlation, warp = cv2.findTransformECC(self.levels[k], frame, (warp / warp[2, 2]).astype(np.float32),
                                                     cv2.MOTION_HOMOGRAPHY, self.criteria, mask, o.smoothing)
        except cv2.error:
            return None
        refined = warp.astype(np.float64) @ np.linalg.inv(scale)
        if not correlation >= o.min_correlation:
            return None
        before = cv2.perspectiveTransform(self.grid.reshape(-1, 1, 2), H).reshape(-1, 2)
        pixels = cv2.perspectiveTransform(self.grid.reshape(-1, 1, 2), refined).reshape(-1, 2)
        inside = mask[np.clip(np.round(before[:, 1]).astype(int), 0, frame.shape[0] - 1),
                      np.clip(np.round(before[:, 0]).astype(int), 0, frame.shape[1] - 1)] > 0
        if np.max(np.linalg.norm(pixels - before, axis=1)[inside], initial=0.0) > o.max_shift_px:
            return None
        fit = fit_planar_pose(self.grid_points, pixels, K, math.inf)
        return None if fit is None else fit.T_camera_target

    def _mask(self, outline: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
        """(H, W) uint8, 255 inside the (4, 2) ``outline`` and ``margin_px`` in from it, 0 elsewhere."""
        outlined = np.zeros(shape[:2], np.uint8)
        cv2.fillConvexPoly(outlined, np.round(outline * 16).astype(np.int32), 255, cv2.LINE_8, 4)
        side = 2 * math.ceil(self.options.margin_px) + 1
        return np.asarray(cv2.erode(outlined, np.ones((side, side), np.uint8)))

    def _outline(self, H: np.ndarray) -> np.ndarray | None:
        """(4, 2) frame pixels of the target's outer corners under ``H``, None when one is behind the camera."""
        w, h = self.target.size_px
        corners = np.array([[-0.5, -0.5, 1.0], [w - 0.5, -0.5, 1.0], [w - 0.5, h - 0.5, 1.0], [-0.5, h - 0.5, 1.0]])
        mapped = corners @ H.T
        if np.any(mapped[:, 2] <= 0):
            return None
        return mapped[:, :2] / mapped[:, 2:]
