"""Pose of a planar target from point correspondences: homography pose, IPPE candidates, scoring.

A target is seen through one or more planar patches (a square marker, a printed image, the
markers of a board, the faces of a box) whose points are known in the target frame. Pixels are
undistorted (a distortion-free pinhole ``K``, (3, 3)); poses are ``T_camera_target`` (4, 4).

Candidates come from OpenCV's IPPE (``cv2.solvePnPGeneric``), which gives the two poses a plane
admits under perspective: the true one and its flip about the line of sight, close in error
when the plane is small or seen nearly face-on. Coplanar points are solved in the plane they
span (``SOLVEPNP_IPPE_SQUARE`` for a lone square patch, ``SOLVEPNP_IPPE`` otherwise) and keep
both solutions; points on several planes are solved patch by patch and only the pose that best
explains all points is kept. Every candidate is scored by the RMS of its reprojection residual
lengths (pixels) over all points; one that puts a point behind the camera is dropped.

``homography_pose`` is the other classical start: the normalised DLT homography of the coplanar
points and the pose it factors into (``services.geometry.homography``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from services.geometry.homography import DegenerateError, homography_dlt, pose_from_homography
from services.geometry.refine import residuals_and_jacobians
from services.geometry.se3 import invert, make_transform, transform_points
from services.geometry.shapes import check_shape

__all__ = [
    "PLANARITY", "Candidate", "Patch", "PlanarView", "homography_pose", "in_plane", "ippe_candidates",
    "ippe_solutions", "normals_at", "plane_frame", "reprojection_rms", "solve_ippe",
]

PLANARITY = 0.01
"""Points are coplanar when all lie within this fraction of their RMS radius of one plane."""


@dataclass(frozen=True)
class Patch:
    """One planar piece of a target: its pose ``T_target_patch`` (4, 4) and its (n, 3) ``points`` in its
    own frame (z = 0, z out of the side the camera sees); ``square``: the points are the corners of a
    square centred on the origin in IPPE_SQUARE's order (-h, h), (h, h), (h, -h), (-h, -h)."""

    T_target_patch: np.ndarray
    points: np.ndarray
    square: bool = False


@dataclass(frozen=True)
class PlanarView:
    """A target's correspondences in one image: (M, 3) ``points`` in the target frame, (M, 2) undistorted
    ``pixels``; ``patches``: the patches the points lie on, in order, each owning ``len(patch.points)``
    consecutive rows of ``points`` and ``pixels``."""

    points: np.ndarray
    pixels: np.ndarray
    patches: tuple[Patch, ...]

    def __post_init__(self) -> None:
        check_shape(self.pixels, f"{len(check_shape(self.points, 'M,3', 'points'))},2", "pixels")


@dataclass(frozen=True)
class Candidate:
    """A pose hypothesis ``T`` (4, 4) ``T_camera_target`` with its RMS residual length ``rms_px`` (pixels)
    and, once refined, ``normal``: ``J^T J`` (6, 6) of its residual Jacobian there."""

    T: np.ndarray
    rms_px: float
    normal: np.ndarray | None = None


def plane_frame(view: PlanarView) -> np.ndarray | None:
    """(4, 4) ``T_target_plane`` whose z = 0 plane holds the view's points (z towards the patches'
    front), or None when they are not coplanar (see ``PLANARITY``). A lone patch's plane is its own frame."""
    if len(view.patches) == 1:
        return view.patches[0].T_target_patch
    points = view.points
    centre = points.mean(axis=0)
    _, _, Vt = np.linalg.svd(points - centre)
    radius = np.sqrt(np.mean(np.sum((points - centre) ** 2, axis=1)))
    if np.max(np.abs((points - centre) @ Vt[2])) > PLANARITY * radius:
        return None
    front = sum(patch.T_target_patch[:3, 2] for patch in view.patches)
    normal = Vt[2] if front @ Vt[2] > 0 else -Vt[2]
    return make_transform(np.column_stack([Vt[0], np.cross(normal, Vt[0]), normal]), centre)


def in_plane(view: PlanarView, T_target_plane: np.ndarray) -> np.ndarray:
    """(M, 3) the view's points in the plane frame ``T_target_plane`` (4, 4), z set to exactly 0."""
    points = transform_points(invert(T_target_plane), view.points)
    points[:, 2] = 0.0
    return points


def reprojection_rms(T: np.ndarray, points: np.ndarray, pixels: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(P,) RMS residual length (pixels) of P poses ``T_camera_target`` (P, 4, 4), each scored on its (P, M, 3)
    target-frame points against (P, M, 2) undistorted pixels; inf where a point is behind the camera."""
    T, K = check_shape(T, "P,4,4", "T"), check_shape(K, "3,3", "K")
    points = check_shape(points, f"{len(T)},M,3", "points")
    pixels = check_shape(pixels, f"{len(T)},{points.shape[1]},2", "pixels")
    p = points @ T[:, :3, :3].transpose(0, 2, 1) + T[:, None, :3, 3]
    positive = p[..., 2] > 0
    residuals = p[..., :2] / np.where(positive, p[..., 2], 1.0)[..., None] @ K[:2, :2].T + K[:2, 2] - pixels
    return np.where(positive.all(axis=1), np.sqrt(np.sum(residuals**2, axis=(1, 2)) / points.shape[1]), np.inf)


def ippe_candidates(views: Sequence[PlanarView], K: np.ndarray) -> list[list[Candidate] | None]:
    """Per view (all of one point count), up to two ``T_camera_target`` candidates, lowest RMS first,
    every point in front of the camera; None when OpenCV's IPPE finds no pose.

    Coplanar points: OpenCV's two IPPE solutions in the plane frame. Otherwise each patch's
    solutions composed with ``T_target_patch^-1``, of which only the best over all points is kept.
    All candidates of all views are scored in one batch. ``K``: (3, 3).
    """
    K = check_shape(K, "3,3", "K")
    rotations, translations, frames, owners = [], [], [], []
    coplanar: list[bool | None] = []
    for i, view in enumerate(views):
        try:
            solutions, flat = ippe_solutions(view, K)
        except DegenerateError:
            coplanar.append(None)
            continue
        coplanar.append(flat)
        for rotvec, translation, T_target_frame in solutions:
            rotations.append(cv2.Rodrigues(rotvec)[0])
            translations.append(translation)
            frames.append(T_target_frame)
            owners.append(i)
    scored: list[list[Candidate]] = [[] for _ in views]
    if owners:
        T_target_frame = np.array(frames)
        T = np.empty((len(owners), 4, 4))
        T[:, 3] = (0.0, 0.0, 0.0, 1.0)
        T[:, :3, :3] = np.array(rotations) @ T_target_frame[:, :3, :3].transpose(0, 2, 1)
        T[:, :3, 3] = np.reshape(translations, (-1, 3)) - (T[:, :3, :3] @ T_target_frame[:, :3, 3:])[..., 0]
        rms = reprojection_rms(T, np.array([views[i].points for i in owners]),
                               np.array([views[i].pixels for i in owners]), K).tolist()
        for k, i in enumerate(owners):
            if rms[k] != math.inf:
                scored[i].append(Candidate(T[k], rms[k]))
    return [None if flat is None else sorted(candidates, key=lambda c: c.rms_px)[:2 if flat else 1]
            for candidates, flat in zip(scored, coplanar, strict=True)]


def ippe_solutions(view: PlanarView, K: np.ndarray) -> tuple[list[tuple[np.ndarray, np.ndarray, np.ndarray]], bool]:
    """OpenCV's IPPE solutions for the view as ``(rvec, tvec, T_target_frame)``: the pose
    ``T_camera_frame`` (rotation vector and translation, (3, 1) each) of the frame the points were
    solved in (their plane, or one patch's), and that frame (4, 4); and whether the points are
    coplanar. DegenerateError when OpenCV refuses the points."""
    if len(view.patches) > 1 and (plane := plane_frame(view)) is not None:
        return [(*solution, plane) for solution in solve_ippe(in_plane(view, plane), view.pixels, K,
                                                              cv2.SOLVEPNP_IPPE)], True
    solutions = []
    start = 0
    for patch in view.patches:
        end = start + len(patch.points)
        flags = cv2.SOLVEPNP_IPPE_SQUARE if patch.square else cv2.SOLVEPNP_IPPE
        solutions += [(*solution, patch.T_target_patch)
                      for solution in solve_ippe(patch.points, view.pixels[start:end], K, flags)]
        start = end
    return solutions, len(view.patches) == 1


def solve_ippe(points: np.ndarray, pixels: np.ndarray, K: np.ndarray,
               flags: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """``(rvec, tvec)`` solutions ((3, 1) each, ``T_camera_plane``) of cv2.solvePnPGeneric for (M, 3) plane
    points (z = 0) and (M, 2) undistorted pixels by the (3, 3) ``K``; DegenerateError when OpenCV refuses the
    points."""
    points = check_shape(points, "M,3", "points")
    pixels, K = check_shape(pixels, f"{len(points)},2", "pixels"), check_shape(K, "3,3", "K")
    try:
        _, rvecs, tvecs, _ = cv2.solvePnPGeneric(points, pixels, K, None, flags=flags)
    except cv2.error as error:
        raise DegenerateError(f"IPPE found no pose: {error.err}") from error
    return list(zip(rvecs, tvecs, strict=True))


def normals_at(T: np.ndarray, views: Sequence[PlanarView], K: np.ndarray) -> np.ndarray:
    """(P, 6, 6) ``J^T J`` of the residual Jacobian of P poses ``T_camera_target`` (P, 4, 4), each on its
    view (all of one point count), by the (3, 3) ``K``."""
    T, K = check_shape(T, f"{len(views)},4,4", "T"), check_shape(K, "3,3", "K")
    _, J = residuals_and_jacobians(T, np.array([v.points for v in views]), np.array([v.pixels for v in views]), K)
    return J.transpose(0, 2, 1) @ J


def homography_pose(view: PlanarView, T_target_plane: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(4, 4) ``T_camera_target`` from the normalised DLT homography of the view's points, coplanar in
    ``T_target_plane`` (see ``plane_frame``); DegenerateError when the points determine none."""
    H = homography_dlt(in_plane(view, T_target_plane)[:, :2], view.pixels)
    return pose_from_homography(H, K) @ invert(T_target_plane)
