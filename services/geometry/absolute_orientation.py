"""Absolute orientation: the rigid transform that carries matched points of one frame onto another.

Given sphere centres ``points_body`` (N, 3) in a body frame and the same spheres measured as
``points_world`` (N, 3) in the world frame (row i of one matched to row i of the other), find
``T_world_body`` with ``points_world ~ R points_body + t``:

* ``three_point_transform``: the closed form from exactly three points (Horn's triad method): an
  orthonormal frame is built on each triangle (x along the first edge, z normal to the triangle,
  y completing it), the rotation is the one taking the body triad onto the world triad, and the
  translation takes the body centroid onto the world centroid.
* ``umeyama_alignment`` / ``least_squares_transform``: the least-squares solution over all points
  (SVD of the cross-covariance, reflection removed; Umeyama 1991, Kabsch without scale). This is
  the default of ``fit_rigid``; ``least_squares_transforms`` solves many matched sets at once.

``fit_rigid`` returns the pose with its residual and a 6x6 covariance propagated to first order
from the (N, 3, 3) covariances of the world points (the body points are taken as exact).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from services.geometry.se3 import make_transform
from services.geometry.shapes import check_shape

__all__ = [
    "METHODS",
    "Method",
    "RigidFit",
    "fit_rigid",
    "least_squares_transform",
    "least_squares_transforms",
    "pose_covariance",
    "pose_covariances",
    "pose_jacobians",
    "three_point_transform",
    "umeyama_alignment",
]

Method = Literal["svd", "three_point"]
METHODS: tuple[str, ...] = ("svd", "three_point")
COLLINEAR_TOLERANCE = 1e-9
"""Smallest accepted ratio of a point set's second extent to its first (a triangle's doubled area to its
squared longest side; the centred points' second singular value to their first)."""


def _matched(points_body: np.ndarray, points_world: np.ndarray, least: int) -> tuple[np.ndarray, np.ndarray]:
    """Both point sets as (N, 3) float64 arrays of the same length N >= ``least``; ValueError otherwise."""
    body = check_shape(points_body, "N,3", "points_body", np.float64)
    world = check_shape(points_world, "N,3", "points_world", np.float64)
    for name, array in (("points_body", body), ("points_world", world)):
        if not np.all(np.isfinite(array)):
            raise ValueError(f"{name} must be finite, got NaN or infinity")
    if len(body) != len(world):
        raise ValueError(f"points_body and points_world must be matched row by row: {len(body)} against "
                         f"{len(world)} points")
    if len(body) < least:
        raise ValueError(f"absolute orientation needs at least {least} matched points, got {len(body)}")
    return body, world


def umeyama_alignment(source: np.ndarray, target: np.ndarray,
                      with_scale: bool = False) -> tuple[np.ndarray, np.ndarray, float]:
    """``(R, t, s)`` minimising ``sum_i |target_i - (s R source_i + t)|^2``.

    ``source``, ``target``: (N, 3) float64 matched points, N >= 2. ``R``: (3, 3) proper rotation,
    ``t``: (3,), ``s``: 1.0 unless ``with_scale``. Closed form of Umeyama (1991): SVD of the
    cross-covariance with the reflection removed. Points on one line leave the rotation about that
    line free; with ``with_scale`` the source points must not all coincide (ValueError).
    """
    src = check_shape(source, "N,3", "source", np.float64)
    dst = check_shape(target, f"{len(src)},3", "target", np.float64)
    mu_src, mu_dst = src.mean(axis=0), dst.mean(axis=0)
    src_c, dst_c = src - mu_src, dst - mu_dst
    U, D, Vt = np.linalg.svd(dst_c.T @ src_c / len(src))
    S = np.ones(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2] = -1.0
    R = U @ np.diag(S) @ Vt
    s = 1.0
    if with_scale:
        variance = float(np.mean(np.sum(src_c**2, axis=1)))
        if variance <= 0.0:
            raise ValueError("a scaled alignment needs source points that are not all the same point")
        s = float(np.dot(D, S) / variance)
    return R, mu_dst - s * R @ mu_src, s


def least_squares_transform(points_body: np.ndarray, points_world: np.ndarray) -> np.ndarray:
    """(4, 4) ``T_world_body`` minimising ``sum_i |points_world_i - T_world_body points_body_i|^2``.

    ``points_body``: (N, 3) float64, body frame; ``points_world``: (N, 3) float64, world frame; N >= 3.
    """
    body, world = _matched(points_body, points_world, 3)
    R, t, _ = umeyama_alignment(body, world)
    return make_transform(R, t)


def least_squares_transforms(points_body: np.ndarray, points_world: np.ndarray,
                             used: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``least_squares_transform`` for P matched sets at once: ``(T_world_body (P, 4, 4), residual RMS (P,) m)``.

    ``points_body``, ``points_world``: (P, N, 3) float64 (body and world frames); ``used``: (P, N) bool,
    the pairs each set is made of (default all; at least 3 per set; the others may hold any finite value).
    One batched SVD of the cross-covariances, the reflection removed as ``umeyama_alignment`` does.
    """
    body = check_shape(points_body, "P,N,3", "points_body", np.float64)
    sets, points = body.shape[:2]
    world = check_shape(points_world, f"{sets},{points},3", "points_world", np.float64)
    weight = np.ones((sets, points)) if used is None else check_shape(used, f"{sets},{points}", "used", np.float64)
    count = weight.sum(axis=1)
    if np.any(count < 3):
        raise ValueError("least_squares_transforms needs at least 3 matched points per set")
    mu_body = np.einsum("pn,pni->pi", weight, body) / count[:, None]
    mu_world = np.einsum("pn,pni->pi", weight, world) / count[:, None]
    centred_body, centred_world = body - mu_body[:, None], world - mu_world[:, None]
    U, _, Vt = np.linalg.svd(np.einsum("pn,pni,pnj->pij", weight, centred_world, centred_body) / count[:, None, None])
    S = np.ones((len(body), 3))
    S[np.linalg.det(U) * np.linalg.det(Vt) < 0, 2] = -1.0
    R = (U * S[:, None, :]) @ Vt
    T = np.tile(np.eye(4), (len(body), 1, 1))
    T[:, :3, :3] = R
    T[:, :3, 3] = mu_world - np.einsum("pij,pj->pi", R, mu_body)
    residual = world - (np.einsum("pij,pnj->pni", R, body) + T[:, None, :3, 3])
    return T, np.sqrt(np.einsum("pn,pn->p", weight, np.sum(residual**2, axis=2)) / count)


def _triad(points: np.ndarray, name: str) -> np.ndarray:
    """(3, 3) orthonormal frame (columns x, y, z) of a triangle: x along p1 - p0, z normal to the triangle."""
    first, second = points[1] - points[0], points[2] - points[0]
    normal = np.cross(first, second)
    longest = max(float(np.sum(first**2)), float(np.sum(second**2)), float(np.sum((points[2] - points[1]) ** 2)))
    if longest == 0.0 or np.linalg.norm(normal) <= COLLINEAR_TOLERANCE * longest:
        raise ValueError(f"{name}: the three points are collinear (or coincide), no frame can be built on them")
    x = first / np.linalg.norm(first)
    z = normal / np.linalg.norm(normal)
    return np.stack([x, np.cross(z, x), z], axis=1)


def three_point_transform(points_body: np.ndarray, points_world: np.ndarray) -> np.ndarray:
    """(4, 4) ``T_world_body`` from three matched points (Horn's triad method).

    ``points_body``: (3, 3) float64, rows are points, body frame; ``points_world``: (3, 3) float64,
    world frame. The rotation takes the body triangle's triad onto the world triangle's; the
    translation takes the body centroid onto the world centroid. Exact for noise-free points.
    """
    body, world = _matched(points_body, points_world, 3)
    if len(body) != 3:
        raise ValueError(f"the three-point method takes exactly 3 matched points, got {len(body)}")
    R = _triad(world, "points_world") @ _triad(body, "points_body").T
    return make_transform(R, world.mean(axis=0) - R @ body.mean(axis=0))


def pose_jacobians(T_world_body: np.ndarray, points_body: np.ndarray) -> np.ndarray:
    """(N, 3, 6) derivatives of the predicted world points ``T_world_body points_body_i`` by the pose.

    The pose perturbation is ``(dtheta, dt)``: ``R = exp([dtheta]x) R_hat`` and ``t = t_hat + dt``,
    both in the world frame (see ``fit_rigid``), so the block is ``[-[R_hat b_i]x, I]``.
    """
    T_world_body = check_shape(T_world_body, "4,4", "T_world_body")
    points_body = check_shape(points_body, "N,3", "points_body", np.float64)
    return _jacobians(T_world_body[None], points_body[None])[0]


def _jacobians(T_world_body: np.ndarray, points_body: np.ndarray) -> np.ndarray:
    """(P, N, 3, 6) ``pose_jacobians`` of P poses (P, 4, 4), each at its own (P, N, 3) body points."""
    rotated = points_body @ T_world_body[:, :3, :3].transpose(0, 2, 1)
    J = np.zeros(rotated.shape + (6,))
    x, y, z = rotated[..., 0], rotated[..., 1], rotated[..., 2]
    J[..., 0, 1], J[..., 0, 2] = z, -y
    J[..., 1, 0], J[..., 1, 2] = -z, x
    J[..., 2, 0], J[..., 2, 1] = y, -x
    J[..., :, 3:] = np.eye(3)
    return J


def pose_covariance(T_world_body: np.ndarray, points_body: np.ndarray, covariances: np.ndarray) -> np.ndarray:
    """(6, 6) first-order covariance of the least-squares pose from (N, 3, 3) world-point covariances.

    The unweighted least-squares estimate moves by ``dx = H^-1 sum_i J_i^T dp_i`` with
    ``H = sum_i J_i^T J_i`` (``J_i`` from ``pose_jacobians``), so its covariance is the sandwich
    ``H^-1 (sum_i J_i^T Sigma_i J_i) H^-1``; it equals the inverse information ``(sum_i J_i^T Sigma_i^-1 J_i)^-1``
    when every ``Sigma_i`` is the same isotropic matrix. Order and frame as in ``fit_rigid``.
    """
    T_world_body = check_shape(T_world_body, "4,4", "T_world_body")
    points_body = check_shape(points_body, "N,3", "points_body", np.float64)
    covariances = check_shape(covariances, f"{len(points_body)},3,3", "covariances", np.float64)
    return pose_covariances(T_world_body[None], points_body[None], covariances[None])[0]


def pose_covariances(T_world_body: np.ndarray, points_body: np.ndarray, covariances: np.ndarray,
                     used: np.ndarray | None = None) -> np.ndarray:
    """(P, 6, 6) ``pose_covariance`` of P poses at once.

    ``T_world_body``: (P, 4, 4); ``points_body``: (P, N, 3) float64, body frame; ``covariances``: (P, N, 3, 3)
    float64 world-point covariances (m^2); ``used``: (P, N) bool, the points each pose was fitted to (default
    all; the others may hold any value).
    """
    T_world_body = check_shape(T_world_body, "P,4,4", "T_world_body", np.float64)
    sets = len(T_world_body)
    points_body = check_shape(points_body, f"{sets},N,3", "points_body", np.float64)
    count = points_body.shape[1]
    sigma = check_shape(covariances, f"{sets},{count},3,3", "covariances", np.float64)
    J = _jacobians(T_world_body, points_body)
    if used is not None:
        used = check_shape(used, f"{sets},{count}", "used", bool)
        J = np.where(used[..., None, None], J, 0.0)
        sigma = np.where(used[..., None, None], sigma, 0.0)
    H = np.einsum("pnki,pnkj->pij", J, J)
    B = np.einsum("pnki,pnkl,pnlj->pij", J, sigma, J)
    H_inv = np.linalg.inv(H)
    covariance = H_inv @ B @ H_inv
    return (covariance + covariance.transpose(0, 2, 1)) / 2


@dataclass(frozen=True)
class RigidFit:
    """A fitted ``T_world_body`` (4, 4); ``residual_rms``: RMS of ``|p_world_i - T p_body_i|`` (m) over the
    ``count`` points used; ``covariance``: (6, 6) or None when no point covariances were given.

    Covariance order and frame: ``(dtheta_x, dtheta_y, dtheta_z, dt_x, dt_y, dt_z)``, radians then metres,
    the true pose being ``R = exp([dtheta]x) R_est`` and ``t = t_est + dt``: a small rotation vector about
    the world axes applied on the left, and the body origin's displacement along the world axes.
    """

    T_world_body: np.ndarray
    residual_rms: float
    count: int
    covariance: np.ndarray | None = None


def fit_rigid(points_body: np.ndarray, points_world: np.ndarray, covariances: np.ndarray | None = None,
              method: Method = "svd") -> RigidFit:
    """Fit ``T_world_body`` to matched points and report its residual and, with ``covariances``, its covariance.

    ``points_body``: (N, 3) float64, body frame; ``points_world``: (N, 3) float64, world frame; N >= 3, not
    all on one line. ``covariances``: (N, 3, 3) float64 covariances of ``points_world`` (m^2), or None.
    ``method``: ``"svd"`` (least squares over all points, the default) or ``"three_point"`` (N = 3 only).
    The covariance (see ``RigidFit``) is that of the least-squares solution (``pose_covariance``).
    """
    body, world = _matched(points_body, points_world, 3)
    spread = np.linalg.svd(body - body.mean(axis=0), compute_uv=False)
    if spread[1] <= COLLINEAR_TOLERANCE * max(spread[0], 1e-300):
        raise ValueError("points_body lie on one line: the rotation about it is not determined")
    if method == "svd":
        T = least_squares_transform(body, world)
    elif method == "three_point":
        T = three_point_transform(body, world)
    else:
        raise ValueError(f"unknown absolute orientation method {method!r} (use {', '.join(METHODS)})")
    residual = world - (body @ T[:3, :3].T + T[:3, 3])
    rms = float(np.sqrt(np.mean(np.sum(residual**2, axis=1))))
    covariance = None if covariances is None else pose_covariance(T, body, covariances)
    return RigidFit(T, rms, len(body), covariance)


def child_frame_covariance(covariance: np.ndarray, T_world_body: np.ndarray) -> np.ndarray:
    """A ``RigidFit`` covariance ((6, 6), world-frame ``(dtheta, dt)``) as ``Pose.covariance`` wants it:
    (6, 6) over ``(tx, ty, tz, rx, ry, rz)`` in the body frame (``T_true = T_est exp(xi)``)."""
    R_t = check_shape(T_world_body, "4,4", "T_world_body", np.float64)[:3, :3].T
    A = np.zeros((6, 6))
    A[:3, 3:] = R_t
    A[3:, :3] = R_t
    return A @ check_shape(covariance, "6,6", "covariance", np.float64) @ A.T
