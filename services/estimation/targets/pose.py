"""The pose of an image target from its points on the target plane and their pixels in a frame.

Recognition (matched keypoints) and tracking (tracked points) both end here, so both publish poses
made the same way:

1. OpenCV's IPPE candidates of the points, scored by their reprojection RMS
   (``services.geometry.planar_pnp``), each refined by Levenberg-Marquardt
   (``services.geometry.refine``); the refined pose with the lowest RMS wins.
2. Points whose residual exceeds ``threshold_px`` at that pose are dropped and the pose is refined
   once more on the rest.
3. The covariance ``sigma^2 (J^T J)^-1`` over (tx, ty, tz, rx, ry, rz) (target frame, metres and
   radians; the perturbation ``services.geometry.refine`` documents), with the per-axis pixel noise
   ``sigma_px`` estimated from the residuals when not given.

Poses are ``T_camera_target`` (4, 4), OpenCV's camera frame; pixels are undistorted (a
distortion-free pinhole ``K``), the centre of the top-left pixel at (0, 0).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from services.geometry.planar_pnp import Patch, PlanarView, ippe_candidates
from services.geometry.refine import pose_covariances, refine_poses

__all__ = ["PlanarFit", "fit_covariance", "fit_planar_pose"]

IDENTITY = np.eye(4)
IDENTITY.flags.writeable = False


@dataclass(frozen=True)
class PlanarFit:
    """``T_camera_target`` (4, 4); ``rms_px``: RMS residual length of the kept points, undistorted pixels;
    ``normal``: (6, 6) ``J^T J`` at the pose; ``kept``: (M,) bool, the points the pose rests on."""

    T_camera_target: np.ndarray
    rms_px: float
    normal: np.ndarray
    kept: np.ndarray


def fit_planar_pose(points: np.ndarray, pixels: np.ndarray, K: np.ndarray, threshold_px: float) -> PlanarFit | None:
    """The pose of (M, 3) float64 target-frame ``points`` (z = 0) seen at (M, 2) float64 undistorted
    ``pixels`` by the pinhole ``K`` (3, 3): the best refined IPPE candidate, refined again without the
    points whose residual exceeds ``threshold_px``. None when no candidate is in front of the camera,
    no refinement converges or fewer than four points are left."""
    candidates = ippe_candidates([PlanarView(points, pixels, (Patch(IDENTITY, points),))], K)[0]
    if not candidates:
        return None
    count = len(candidates)
    result = refine_poses(np.array([c.T for c in candidates]), np.broadcast_to(points, (count, *points.shape)),
                          np.broadcast_to(pixels, (count, *pixels.shape)), K)
    usable = np.flatnonzero(result.converged)
    if not len(usable):
        return None
    best = usable[np.argmin(result.rms_px[usable])]
    T = result.T[best]
    projected = points @ T[:3, :3].T + T[:3, 3]
    residuals = projected[:, :2] / projected[:, 2:] @ K[:2, :2].T + K[:2, 2] - pixels
    kept = np.sum(residuals**2, axis=1) <= threshold_px**2
    if kept.all():
        return PlanarFit(T, float(result.rms_px[best]), result.normal[best], kept)
    if kept.sum() < 4:
        return None
    again = refine_poses(T[None], points[kept][None], pixels[kept][None], K)
    if not again.converged[0]:
        return None
    return PlanarFit(again.T[0], float(again.rms_px[0]), again.normal[0], kept)


def fit_covariance(fit: PlanarFit, sigma_px: float | None = None) -> np.ndarray | None:
    """(6, 6) covariance of ``fit``'s pose over (tx, ty, tz, rx, ry, rz), target frame, metres and
    radians; ``sigma_px``: per-axis pixel noise, None to estimate it as ``rms * sqrt(N / (2N - 6))``
    from the N kept points' residuals. None when the points do not constrain all six parameters."""
    n = int(fit.kept.sum())
    sigma = sigma_px if sigma_px is not None else fit.rms_px * math.sqrt(n / max(2 * n - 6, 1))
    covariance, regular = pose_covariances(fit.normal[None], sigma)
    return covariance[0] if regular[0] else None
