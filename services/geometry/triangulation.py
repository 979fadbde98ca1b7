"""Triangulation of one 3D point from its pixels in several calibrated cameras.

World = the frame the cameras' ``T_rig_camera`` poses are given in (a rig's frame). Linear DLT
over all views (on ideal pinhole pixels), the midpoint of two rays, and a Gauss-Newton
refinement of the reprojection error through each camera's distortion, which also yields the
point's covariance ``(J^T J)^-1 sigma_px^2`` (J: residuals, px, with respect to the point, m).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from services.geometry.camera import CameraModel, undistort_pixels
from services.geometry.se3 import invert

__all__ = ["TriangulatedPoint", "projection_matrix", "triangulate_dlt", "triangulate_midpoint", "camera_rays",
           "reproject", "refine_point", "triangulate"]


@dataclass(frozen=True)
class TriangulatedPoint:
    """A point triangulated from ``views`` observations.

    ``point``: (3,) world frame, m; ``rms_px``: root mean square over the views of the
    reprojection error's length, px; ``covariance``: (3, 3) m^2, world frame;
    ``camera_indices`` / ``blob_indices``: for each view used, the camera's index and the
    observation's index in that camera's list (same length, cameras distinct).
    """

    point: np.ndarray
    rms_px: float
    covariance: np.ndarray
    camera_indices: tuple[int, ...]
    blob_indices: tuple[int, ...]

    @property
    def views(self) -> int:
        return len(self.camera_indices)


def projection_matrix(K: np.ndarray, T_camera_world: np.ndarray) -> np.ndarray:
    """(3, 4) ``P = K [R | t]`` taking homogeneous world points to homogeneous ideal pixels."""
    return np.asarray(K, dtype=np.float64) @ np.asarray(T_camera_world, dtype=np.float64)[:3, :]


def triangulate_dlt(projections: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """(3,) world point minimising the algebraic error of ``x ~ P X`` over all views.

    ``projections``: (V, 3, 4); ``pixels``: (V, 2) ideal pinhole pixels; V >= 2. Each view's two
    rows are scaled to unit norm so that no camera dominates by its scale. A point at infinity
    (homogeneous w = 0) gives ValueError.
    """
    projections = np.asarray(projections, dtype=np.float64).reshape(-1, 3, 4)
    pixels = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    if len(projections) < 2 or len(projections) != len(pixels):
        raise ValueError(f"triangulate_dlt needs (V, 3, 4) projections and (V, 2) pixels with V >= 2, got "
                         f"{projections.shape} and {pixels.shape}")
    rows = np.concatenate([pixels[:, :1] * projections[:, 2] - projections[:, 0],
                           pixels[:, 1:] * projections[:, 2] - projections[:, 1]])
    rows /= np.linalg.norm(rows, axis=1, keepdims=True)
    X = np.linalg.svd(rows)[2][-1]
    if abs(X[3]) < 1e-12 * np.linalg.norm(X):
        raise ValueError("triangulate_dlt: the rays are parallel (point at infinity)")
    return X[:3] / X[3]


def triangulate_midpoint(origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """(3,) midpoint of the shortest segment between two rays ``origins[k] + s * directions[k]``.

    ``origins``, ``directions``: (2, 3), world frame (directions need not be unit). Parallel rays
    give ValueError.
    """
    o = np.asarray(origins, dtype=np.float64).reshape(2, 3)
    d = np.asarray(directions, dtype=np.float64).reshape(2, 3)
    A = np.array([[d[0] @ d[0], -d[0] @ d[1]], [d[0] @ d[1], -d[1] @ d[1]]])
    b = np.array([d[0] @ (o[1] - o[0]), d[1] @ (o[1] - o[0])])
    if abs(np.linalg.det(A)) < 1e-12 * (d[0] @ d[0]) * (d[1] @ d[1]):
        raise ValueError("triangulate_midpoint: the rays are parallel")
    s, u = np.linalg.solve(A, b)
    return 0.5 * (o[0] + s * d[0] + o[1] + u * d[1])


def camera_rays(camera: CameraModel, pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(origin (3,), directions (N, 3))``, world frame, of the rays through (N, 2) observed pixels
    of ``camera`` (its distortion undone); directions are unit vectors."""
    ideal = undistort_pixels(pixels, camera.K, camera.dist)
    rays_cam = np.hstack([ideal, np.ones((len(ideal), 1))]) @ np.linalg.inv(camera.K).T
    directions = rays_cam @ camera.T_rig_camera[:3, :3].T
    return camera.T_rig_camera[:3, 3].copy(), directions / np.linalg.norm(directions, axis=1, keepdims=True)


def _view_jacobians(camera: CameraModel, points_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(pixels (N, 2), jacobians (N, 2, 3))``: observed-pixel projections of (N, 3) world points and
    their derivatives with respect to the world point, through the camera's distortion.

    cv2.projectPoints differentiates with respect to the translation; a world point moves the
    camera-frame point by ``R_camera_world`` times its displacement, as the translation would.
    """
    T_camera_world = invert(camera.T_rig_camera)
    rvec = cv2.Rodrigues(T_camera_world[:3, :3])[0]
    pixels, jacobian = cv2.projectPoints(points_world.reshape(-1, 1, 3), rvec, T_camera_world[:3, 3],
                                         camera.K, camera.dist)
    d_translation = jacobian[:, 3:6].reshape(-1, 2, 3)
    return pixels.reshape(-1, 2), d_translation @ T_camera_world[:3, :3]


def reproject(camera: CameraModel, points_world: np.ndarray) -> np.ndarray:
    """(N, 2) observed pixels (through the distortion) of (N, 3) world points; (N,) depths <= 0 give NaN."""
    points_world = np.asarray(points_world, dtype=np.float64).reshape(-1, 3)
    if len(points_world) == 0:
        return np.zeros((0, 2))
    T_camera_world = invert(camera.T_rig_camera)
    depth = points_world @ T_camera_world[2, :3] + T_camera_world[2, 3]
    pixels = _view_jacobians(camera, points_world)[0]
    pixels[depth <= 0] = np.nan
    return pixels


def refine_point(cameras: Sequence[CameraModel], pixels: np.ndarray, point: np.ndarray,
                 iterations: int = 10) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Gauss-Newton on the reprojection error of one world point seen by ``cameras``.

    ``pixels``: (V, 2) observed pixels (distorted), ``pixels[k]`` in ``cameras[k]``; ``point``:
    (3,) start, world frame. Returns ``(point (3,), residuals (V, 2) observed - projected px,
    jacobian (2V, 3) of the residuals with respect to the point, px/m)``. A step that does not
    lower the error ends the iterations.
    """
    pixels = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    point = np.asarray(point, dtype=np.float64).reshape(3).copy()

    def evaluate(X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        rows = [_view_jacobians(camera, X) for camera in cameras]
        residuals = pixels - np.array([r[0][0] for r in rows])
        jacobian = -np.concatenate([r[1][0] for r in rows])
        return residuals, jacobian

    residuals, jacobian = evaluate(point)
    for _ in range(iterations):
        step = np.linalg.lstsq(jacobian, -residuals.ravel(), rcond=None)[0]
        candidate = point + step
        new_residuals, new_jacobian = evaluate(candidate)
        if np.sum(new_residuals ** 2) > np.sum(residuals ** 2):
            break
        point, residuals, jacobian = candidate, new_residuals, new_jacobian
        if np.linalg.norm(step) < 1e-10:
            break
    return point, residuals, jacobian


def triangulate(cameras: Sequence[CameraModel], pixels: np.ndarray, sigma_px: float,
                camera_indices: Sequence[int] | None = None,
                blob_indices: Sequence[int] | None = None) -> TriangulatedPoint:
    """One world point from (V, 2) observed pixels, ``pixels[k]`` in ``cameras[k]`` (V >= 2):
    DLT on the undistorted pixels, then ``refine_point``; covariance ``(J^T J)^-1 sigma_px^2``
    for pixel noise of ``sigma_px`` per coordinate. The indices are carried into the result
    (default: 0..V-1 and zeros)."""
    pixels = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    ideal = np.array([undistort_pixels(p, c.K, c.dist)[0] for c, p in zip(cameras, pixels, strict=True)])
    projections = np.array([projection_matrix(c.K, invert(c.T_rig_camera)) for c in cameras])
    point, residuals, jacobian = refine_point(cameras, pixels, triangulate_dlt(projections, ideal))
    information = jacobian.T @ jacobian
    covariance = np.linalg.pinv(information) * sigma_px ** 2
    views = len(cameras)
    return TriangulatedPoint(
        point=point, rms_px=float(np.sqrt(np.mean(np.sum(residuals ** 2, axis=1)))), covariance=covariance,
        camera_indices=tuple(int(i) for i in (camera_indices if camera_indices is not None else range(views))),
        blob_indices=tuple(int(i) for i in (blob_indices if blob_indices is not None else [0] * views)),
    )
