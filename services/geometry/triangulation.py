"""Triangulation of one 3D point from its pixels in several calibrated cameras.

World = the frame the cameras' ``T_rig_camera`` poses are given in (a rig's frame). Linear DLT
over all views (on ideal pinhole pixels), the midpoint of two rays, and a Gauss-Newton
refinement of the reprojection error through each camera's distortion, which also yields the
point's covariance ``(J^T J)^-1 sigma_px^2`` (J: residuals, px, with respect to the point, m).
The ``*_many`` forms do the same for N points at once, each seen by its own subset of the
cameras of a ``CameraStack``: ``triangulate_dlt_many`` in one batched SVD, ``triangulate_many`` (DLT,
Gauss-Newton, covariance) point by point in compiled code (``services.geometry.triangulation_kernel``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from services.geometry.camera import CameraModel, undistort_pixels
from services.geometry.camera_stack import CameraStack
from services.geometry.se3 import invert
from services.geometry.shapes import check_shape
from services.geometry.triangulation_kernel import triangulate_points

__all__ = ["TriangulatedPoint", "Triangulation", "projection_matrix", "triangulate_dlt", "triangulate_dlt_many",
           "triangulate_midpoint", "meet_in_front", "camera_rays", "reproject", "triangulate",
           "triangulate_many"]

STEP_TOLERANCE_M = 1e-10
"""Gauss-Newton stops at a step shorter than this (m): the point is where it would stay."""
GAUSS_NEWTON_ITERATIONS = 10
"""The most Gauss-Newton steps ``triangulate_many`` takes per point."""


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
    """(3, 4) ``P = K [R | t]`` of the (3, 3) ``K`` and (4, 4) ``T_camera_world``, taking homogeneous world points
    to homogeneous ideal pixels."""
    return (check_shape(K, "3,3", "K", np.float64)
            @ check_shape(T_camera_world, "4,4", "T_camera_world", np.float64)[:3, :])


def triangulate_dlt(projections: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """(3,) world point minimising the algebraic error of ``x ~ P X`` over all views.

    ``projections``: (V, 3, 4); ``pixels``: (V, 2) ideal pinhole pixels; V >= 2. Each view's two
    rows are scaled to unit norm so that no camera dominates by its scale. A point at infinity
    (homogeneous w = 0) gives ValueError.
    """
    projections = check_shape(projections, "V,3,4", "projections", np.float64)
    pixels = check_shape(pixels, f"{len(projections)},2", "pixels", np.float64)
    if len(projections) < 2:
        raise ValueError(f"triangulate_dlt needs V >= 2 views, got {len(projections)}")
    point = triangulate_dlt_many(projections, pixels[None], np.ones((1, len(pixels)), bool))[0]
    if not np.all(np.isfinite(point)):
        raise ValueError("triangulate_dlt: the rays are parallel (point at infinity)")
    return point


def triangulate_dlt_many(projections: np.ndarray, pixels: np.ndarray, seen: np.ndarray) -> np.ndarray:
    """(N, 3) world points, each by ``triangulate_dlt`` over the views it is seen in; NaN for a point
    at infinity (or seen fewer than twice).

    ``projections``: (C, 3, 4) of C cameras; ``pixels``: (N, C, 2) ideal pinhole pixels (any value
    where unseen); ``seen``: (N, C) bool. One batched SVD for all points.
    """
    projections = check_shape(projections, "C,3,4", "projections")
    pixels = check_shape(pixels, f"N,{len(projections)},2", "pixels", np.float64)
    seen = check_shape(seen, f"{len(pixels)},{len(projections)}", "seen")
    rows = np.concatenate([pixels[..., :1] * projections[:, 2] - projections[:, 0],
                           pixels[..., 1:] * projections[:, 2] - projections[:, 1]], axis=1)
    norms = np.maximum(np.linalg.norm(rows, axis=2, keepdims=True), 1e-300)
    rows = np.where(np.tile(seen, 2)[..., None], rows / norms, 0.0)
    X = np.linalg.svd(rows)[2][:, -1]
    at_infinity = (np.abs(X[:, 3]) < 1e-12 * np.linalg.norm(X, axis=1)) | (np.count_nonzero(seen, axis=1) < 2)
    with np.errstate(divide="ignore", invalid="ignore"):
        points = X[:, :3] / X[:, 3:]
    points[at_infinity] = np.nan
    return points


def triangulate_midpoint(origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """(3,) midpoint of the shortest segment between two rays ``origins[k] + s * directions[k]``.

    ``origins``, ``directions``: (2, 3), world frame (directions need not be unit). Parallel rays
    give ValueError.
    """
    o = check_shape(origins, "2,3", "origins", np.float64)
    d = check_shape(directions, "2,3", "directions", np.float64)
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


def reproject(camera: CameraModel, points_world: np.ndarray) -> np.ndarray:
    """(N, 2) observed pixels (through the distortion) of (N, 3) world points; (N,) depths <= 0 give NaN."""
    points_world = check_shape(points_world, "*,3", "points_world", np.float64).reshape(-1, 3)
    if len(points_world) == 0:
        return np.zeros((0, 2))
    T_camera_world = invert(camera.T_rig_camera)
    depth = points_world @ T_camera_world[2, :3] + T_camera_world[2, 3]
    rvec = cv2.Rodrigues(T_camera_world[:3, :3])[0]
    pixels = cv2.projectPoints(points_world.reshape(-1, 1, 3), rvec, T_camera_world[:3, 3], camera.K,
                               camera.dist)[0].reshape(-1, 2)
    pixels[depth <= 0] = np.nan
    return pixels


@dataclass(frozen=True)
class Triangulation:
    """N points triangulated at once (``triangulate_many``): ``points`` (N, 3) world frame, m (NaN
    where the rays are parallel); ``residuals`` (N, C, 2) observed - projected px, zero where
    unseen; ``rms_px`` (N,) over each point's views (inf where it failed); ``covariances`` (N, 3, 3) m^2
    (NaN where it failed)."""

    points: np.ndarray
    residuals: np.ndarray
    rms_px: np.ndarray
    covariances: np.ndarray


def triangulate_many(stack: CameraStack, pixels: np.ndarray, seen: np.ndarray, sigma_px: float,
                     ideal: np.ndarray | None = None, start: np.ndarray | None = None) -> Triangulation:
    """``triangulate`` for N points at once, each from the cameras of ``stack`` it is seen in.

    ``pixels``: (N, C, 2) observed pixels (distorted; any value where unseen); ``seen``: (N, C)
    bool, at least two per point; ``ideal``: the same pixels undistorted when already known;
    ``start``: (N, 3) their DLT points (``triangulate_dlt_many``) when already known.
    """
    pixels = check_shape(pixels, f"N,{len(stack)},2", "pixels", np.float64)
    seen = check_shape(seen, f"{len(pixels)},{len(stack)}", "seen", bool)
    if len(pixels) == 0:
        return Triangulation(np.zeros((0, 3)), np.zeros((0, len(stack), 2)), np.zeros(0), np.zeros((0, 3, 3)))
    if ideal is None and start is None:
        ideal = np.zeros_like(pixels)
        for c in range(len(stack)):
            ideal[seen[:, c], c] = undistort_pixels(pixels[seen[:, c], c], stack.K[c], stack.dist[c])
    ideal = pixels if ideal is None else check_shape(ideal, f"{len(pixels)},{len(stack)},2", "ideal", np.float64)
    start = None if start is None else check_shape(start, f"{len(pixels)},3", "start", np.float64)
    points, residuals, rms, covariances = triangulate_points(
        stack.K, stack.dist, stack.R_camera_world, stack.t_camera_world, stack.projections, pixels, ideal, seen, start,
        sigma_px, GAUSS_NEWTON_ITERATIONS, STEP_TOLERANCE_M)
    return Triangulation(points, residuals, rms, covariances)


def triangulate(cameras: Sequence[CameraModel], pixels: np.ndarray, sigma_px: float,
                camera_indices: Sequence[int] | None = None,
                blob_indices: Sequence[int] | None = None) -> TriangulatedPoint:
    """One world point from (V, 2) observed pixels, ``pixels[k]`` in ``cameras[k]`` (V >= 2):
    DLT on the undistorted pixels, then Gauss-Newton on the reprojection error; covariance ``(J^T J)^-1 sigma_px^2``
    for pixel noise of ``sigma_px`` per coordinate. The indices are carried into the result
    (default: 0..V-1 and zeros). Rays that meet at infinity give ValueError."""
    pixels = check_shape(pixels, f"{len(cameras)},2", "pixels", np.float64)[None]
    found = triangulate_many(CameraStack.of(cameras), pixels, np.ones(pixels.shape[:2], bool), sigma_px)
    if not np.all(np.isfinite(found.points[0])):
        raise ValueError("triangulate: the rays are parallel (point at infinity)")
    views = len(cameras)
    return TriangulatedPoint(
        point=found.points[0], rms_px=float(found.rms_px[0]), covariance=found.covariances[0],
        camera_indices=tuple(int(i) for i in (camera_indices if camera_indices is not None else range(views))),
        blob_indices=tuple(int(i) for i in (blob_indices if blob_indices is not None else [0] * views)),
    )


def meet_in_front(K: np.ndarray, T_a: np.ndarray, T_b: np.ndarray, pixels_a: np.ndarray, pixels_b: np.ndarray,
                  rows: np.ndarray, columns: np.ndarray) -> np.ndarray:
    """(P,) bool: whether the rays through ``pixels_a[rows]`` ((Na, 2) px) of camera ``T_a`` and
    ``pixels_b[columns]`` ((Nb, 2) px) of ``T_b`` (``T_camera_world``, both (4, 4), intrinsics ``K``)
    come closest in front of both cameras.

    With ``c`` the baseline from a's centre to b's and the world rays ``u``, ``v``, the distances along
    each ray to the closest points have the signs of ``(c x v).(u x v) = (c.u)(v.v) - (c.v)(u.v)``
    and ``(c x u).(u x v) = (c.u)(u.v) - (c.v)(u.u)`` (the Binet-Cauchy identity): per pair only
    ``u.v`` is computed, the rest once per pixel."""
    K, T_a, T_b = check_shape(K, "3,3", "K"), check_shape(T_a, "4,4", "T_a"), check_shape(T_b, "4,4", "T_b")
    pixels_a, pixels_b = check_shape(pixels_a, "N,2", "pixels_a"), check_shape(pixels_b, "N,2", "pixels_b")
    K_inv = np.linalg.inv(K)
    rays_a = (np.hstack([pixels_a, np.ones((len(pixels_a), 1))]) @ K_inv.T) @ T_a[:3, :3]
    rays_b = (np.hstack([pixels_b, np.ones((len(pixels_b), 1))]) @ K_inv.T) @ T_b[:3, :3]
    baseline = -T_b[:3, :3].T @ T_b[:3, 3] + T_a[:3, :3].T @ T_a[:3, 3]
    cu, cv = (rays_a @ baseline)[rows], (rays_b @ baseline)[columns]
    uu, vv = np.sum(rays_a**2, axis=1)[rows], np.sum(rays_b**2, axis=1)[columns]
    uv = np.einsum("ij,ij->i", rays_a[rows], rays_b[columns])
    depth_a = cu * vv - cv * uv
    depth_b = cu * uv - cv * uu
    return (depth_a > 0) & (depth_b > 0)
