"""Levenberg-Marquardt refinement of camera-object poses by reprojection error, and their covariance.

A pose is ``T_camera_object`` (4, 4): it maps (N, 3) object points (object frame, metres)
into the camera frame, where a distortion-free pinhole ``K`` (3, 3) projects them to (N, 2)
pixels. Undistort observed pixels first (``cv2.undistortPoints(..., P=K)``).

Updates are right perturbations in the object (child) frame, ``T <- T @ D(delta)`` with
``delta = (tx, ty, tz, rx, ry, rz)`` (metres, then a rotation vector in radians) and the
simple increment ``D(delta) = [R(r) | t]`` rather than the full SE(3) exponential. Both agree
to first order, so the Jacobian at ``delta = 0`` and the covariance built from it are those of
the perturbation ``protocol.poses.Pose.covariance`` documents.

``refine_poses`` runs B independent problems of the same point count at once: every numpy
call works on all the problems still iterating, so the per-call overhead of tiny arrays is
paid once per iteration rather than once per problem. Each problem keeps its own damping
and stopping test and follows exactly the steps it would take alone; ``refine_pose`` is the
one-problem case.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.geometry.homography import DegenerateError

INITIAL_DAMPING = 1e-3
MIN_DAMPING = 1e-12
MAX_DAMPING = 1e12
SKEW = np.array([[[0, 0, 0], [0, 0, -1], [0, 1, 0]],
                 [[0, 0, 1], [0, 0, 0], [-1, 0, 0]],
                 [[0, -1, 0], [1, 0, 0], [0, 0, 0]]], dtype=np.float64).reshape(3, 9)
"""``w @ SKEW`` is the cross-product matrix ``[w]x`` of (B, 3) vectors, flattened to (B, 9)."""


@dataclass(frozen=True)
class RefineResult:
    """``T``: (4, 4) refined ``T_camera_object``; ``rms_px``: RMS of the (N,) point residual
    lengths, pixels; ``iterations``: LM iterations run; ``jacobian``: (2N, 6) derivative of the
    residuals (u0, v0, u1, v1, ...) with respect to ``delta`` at ``T``; ``converged``: the
    stopping test was met before the iteration limit."""

    T: np.ndarray
    rms_px: float
    iterations: int
    jacobian: np.ndarray
    converged: bool


@dataclass(frozen=True)
class RefineResults:
    """B refinements: ``T`` (B, 4, 4), ``rms_px`` (B,), ``iterations`` (B,) int, ``jacobian`` (B, 2N, 6)
    and ``normal`` (B, 6, 6) = ``J^T J`` at ``T``, ``converged`` (B,) bool as in ``RefineResult``;
    ``degenerate`` (B,) bool: the points do not constrain all six pose parameters (the problem
    stopped there, not converged, at its last accepted pose)."""

    T: np.ndarray
    rms_px: np.ndarray
    iterations: np.ndarray
    jacobian: np.ndarray
    normal: np.ndarray
    converged: np.ndarray
    degenerate: np.ndarray


def residuals_and_jacobian(T: np.ndarray, points_obj: np.ndarray, pixels: np.ndarray,
                           K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(r, J)``: (2N,) residuals ``project(T @ X) - pixels`` and their (2N, 6) analytic Jacobian.

    ``points_obj``: (N, 3) object frame; ``pixels``: (N, 2); ``K``: (3, 3). Points need z > 0.
    One problem of ``stacked_residuals_and_jacobians``.
    """
    T = np.asarray(T, dtype=np.float64)
    points_obj = np.asarray(points_obj, dtype=np.float64).reshape(1, -1, 3)
    pixels = np.asarray(pixels, dtype=np.float64).reshape(1, -1, 2)
    augmented, _ = stacked_residuals_and_jacobians(T[None, :3, :3], T[None, :3, 3], points_obj, pixels,
                                                   np.asarray(K, dtype=np.float64))
    flat = augmented.reshape(-1, 7)
    return flat[:, 6].copy(), flat[:, :6].copy()


def stacked_residuals_and_jacobians(R: np.ndarray, t: np.ndarray, points_obj: np.ndarray, pixels: np.ndarray,
                                    K: np.ndarray, basis: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``(A, front)`` for B poses ``T = [R | t]`` (R: (B, 3, 3), t: (B, 3)), each with its own (B, N, 3)
    ``points_obj`` (object frame) and (B, N, 2) ``pixels``, under one ``K`` (3, 3).

    ``A``: (B, N, 2, 7), per point and pixel axis the Jacobian row (6) of the residual with
    respect to ``delta``, then the residual ``project(T @ X) - pixel``; reshaped to (B, 2N, 7) it
    is ``[J | r]``. ``front``: (B,) every point has z > 0 (where one has not, that pose's ``A`` is
    meaningless). Per point, with ``p = R X + t`` in the camera frame, ``dp/ddelta = R [I, -[X]x]``
    (``basis``, (B, N, 3, 6), is ``[I, -[X]x]``; pass it to save its computation) and the
    projection adds ``(1/z) [K2 | -K2 (x/z, y/z)]`` with ``K2 = K[:2, :2]``.
    """
    if basis is None:
        basis = point_basis(points_obj)
    p = points_obj @ R.transpose(0, 2, 1) + t[:, None, :]
    positive = p[..., 2] > 0
    inverse_z = 1.0 / np.where(positive, p[..., 2], 1.0)
    centred = (p[..., :2] * inverse_z[..., None]) @ K[:2, :2].T
    augmented = np.empty((*p.shape[:2], 2, 7))
    augmented[..., 6] = centred + K[:2, 2] - pixels
    projection = np.empty((*p.shape[:2], 2, 3))
    projection[..., :2] = K[:2, :2]
    projection[..., 2] = -centred
    projection *= inverse_z[..., None, None]
    np.matmul(projection @ R[:, None], basis, out=augmented[..., :6])
    return augmented, np.all(positive, axis=1)


def point_basis(points_obj: np.ndarray) -> np.ndarray:
    """(B, N, 3, 6) ``[I, -[X]x]``, the derivative of ``D(delta) @ X`` at ``delta = 0``, of (B, N, 3) points."""
    basis = np.zeros((*points_obj.shape[:2], 3, 6))
    basis[..., :3] = np.eye(3)
    basis[..., 3:] = -(points_obj @ SKEW).reshape(*points_obj.shape[:2], 3, 3)
    return basis


def rotations_from_rotvecs(rotvecs: np.ndarray) -> np.ndarray:
    """(B, 3, 3) rotations of (B, 3) rotation vectors (axis * angle, radians): Rodrigues' formula as
    cv2.Rodrigues evaluates it (identity below an angle of machine epsilon)."""
    angle = np.sqrt(np.sum(rotvecs * rotvecs, axis=1))
    axis = rotvecs * np.divide(1.0, angle, out=np.zeros_like(angle), where=angle >= np.finfo(float).eps)[:, None]
    cos = np.cos(angle)[:, None, None]
    outer = axis[:, :, None] * axis[:, None, :]
    cross = (axis @ SKEW).reshape(-1, 3, 3)
    return cos * np.eye(3) + (1 - cos) * outer + np.sin(angle)[:, None, None] * cross


def refine_pose(T: np.ndarray, points_obj: np.ndarray, pixels: np.ndarray, K: np.ndarray,
                max_iterations: int = 100, tolerance: float = 1e-10) -> RefineResult:
    """Refine ``T_camera_object`` (4, 4) to minimise the reprojection error of (N, 3) ``points_obj``
    (object frame) against (N, 2) undistorted ``pixels`` under the pinhole ``K``; N >= 3.

    The method is ``refine_poses``'s. Raises ValueError when a point lies behind the camera at
    the start, DegenerateError when the points do not constrain the pose (e.g. all on one line
    of sight).
    """
    result = refine_poses(np.asarray(T, dtype=np.float64)[None], np.asarray(points_obj, dtype=np.float64)[None],
                          np.asarray(pixels, dtype=np.float64)[None], K, max_iterations, tolerance)
    if result.degenerate[0]:
        raise DegenerateError("the points do not constrain all six pose parameters")
    return RefineResult(result.T[0], float(result.rms_px[0]), int(result.iterations[0]), result.jacobian[0],
                        bool(result.converged[0]))


def refine_poses(T: np.ndarray, points_obj: np.ndarray, pixels: np.ndarray, K: np.ndarray,
                 max_iterations: int = 100, tolerance: float = 1e-10) -> RefineResults:
    """Refine B poses ``T_camera_object`` (B, 4, 4), each against its own (B, N, 3) ``points_obj``
    (object frame) and (B, N, 2) undistorted ``pixels``, under one pinhole ``K``; N >= 3.

    Per problem: Marquardt's damping (``lambda * diag(J^T J)``, so the metre and radian columns
    need no common scale), lambda divided by 10 on an accepted step and multiplied by 10 on a
    rejected one; a step that puts a point behind the camera is rejected. Stops when a step
    changes the cost by less than ``tolerance`` relatively, when the step is below
    ``tolerance`` (metres / radians), or when lambda has grown beyond any useful step; a
    problem whose damped normal equations are singular stops as ``degenerate``.
    Raises ValueError when a point lies behind the camera at a start, DegenerateError when
    the shapes do not give N >= 3 matching points.
    """
    T = np.asarray(T, dtype=np.float64).reshape(-1, 4, 4)
    count = len(T)
    points_obj = np.asarray(points_obj, dtype=np.float64).reshape(count, -1, 3)
    pixels = np.asarray(pixels, dtype=np.float64).reshape(count, -1, 2)
    K = np.asarray(K, dtype=np.float64)
    n = points_obj.shape[1]
    if pixels.shape[1] != n or n < 3:
        raise DegenerateError(f"need N >= 3 matching points, got {n} and {pixels.shape[1]}")
    R, t, basis = T[:, :3, :3].copy(), T[:, :3, 3].copy(), point_basis(points_obj)
    augmented, front = stacked_residuals_and_jacobians(R, t, points_obj, pixels, K, basis)
    if not np.all(front):
        raise ValueError("a point lies behind the camera at the initial pose")
    normal = normal_equations(augmented)
    final_R, final_t, final_augmented, final_normal = R.copy(), t.copy(), augmented.copy(), normal.copy()
    iterations, converged, degenerate = np.zeros(count, dtype=np.int64), np.zeros(count, bool), np.zeros(count, bool)
    rows, cost, damping = np.arange(count), normal[:, 6, 6].copy(), np.full(count, INITIAL_DAMPING)
    iteration = 0
    while len(rows) and iteration < max_iterations:
        iteration += 1
        step, solved = damped_steps(normal, damping)
        increment_R = rotations_from_rotvecs(step[:, 3:])
        candidate_R, candidate_t = R @ increment_R, (R @ step[:, :3, None])[..., 0] + t
        candidate, front = stacked_residuals_and_jacobians(candidate_R, candidate_t, points_obj, pixels, K, basis)
        candidate_normal = normal_equations(candidate)
        candidate_cost = np.where(front, candidate_normal[:, 6, 6], np.inf)
        accept = candidate_cost <= cost
        done = (np.max(np.abs(step), axis=1) < tolerance) | np.where(
            accept, cost - candidate_cost <= tolerance * cost, damping * 10 > MAX_DAMPING)
        R = np.where(accept[:, None, None], candidate_R, R)
        t = np.where(accept[:, None], candidate_t, t)
        augmented = np.where(accept[:, None, None, None], candidate, augmented)
        normal = np.where(accept[:, None, None], candidate_normal, normal)
        cost = np.where(accept, candidate_cost, cost)
        damping = np.where(accept, np.maximum(damping / 10, MIN_DAMPING), damping * 10)
        finished = (done & solved) | ~solved | (iteration >= max_iterations)
        if np.any(finished):
            ended = rows[finished]
            final_R[ended], final_t[ended], final_augmented[ended], final_normal[ended] = \
                R[finished], t[finished], augmented[finished], normal[finished]
            iterations[ended], converged[ended], degenerate[ended] = iteration, (done & solved)[finished], \
                ~solved[finished]
            keep = ~finished
            rows, R, t, augmented, normal, cost, damping = \
                rows[keep], R[keep], t[keep], augmented[keep], normal[keep], cost[keep], damping[keep]
            points_obj, pixels, basis = points_obj[keep], pixels[keep], basis[keep]
    final_T = np.tile(np.eye(4), (count, 1, 1))
    final_T[:, :3, :3], final_T[:, :3, 3] = final_R, final_t
    return RefineResults(final_T, np.sqrt(final_normal[:, 6, 6] / n), iterations,
                         final_augmented[..., :6].reshape(count, 2 * n, 6), final_normal[:, :6, :6].copy(),
                         converged, degenerate)


def normal_equations(augmented: np.ndarray) -> np.ndarray:
    """(B, 7, 7) ``[J | r]^T [J | r]`` of (B, N, 2, 7) ``[J | r]`` rows: ``J^T J``, ``J^T r`` and the cost ``r^T r``."""
    flat = augmented.reshape(len(augmented), -1, 7)
    return flat.transpose(0, 2, 1) @ flat


def damped_steps(normal: np.ndarray, damping: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(step, solved)``: (B, 6) solutions of ``(J^T J + lambda diag(J^T J)) step = -J^T r`` from (B, 7, 7)
    ``normal_equations`` and (B,) ``damping`` lambda, and (B,) whether each system was regular (a
    singular one gets a zero step)."""
    damped = normal[:, :6, :6] * (1 + damping[:, None, None] * np.eye(6))
    gradient = -normal[:, :6, 6:]
    try:
        return np.linalg.solve(damped, gradient)[..., 0], np.ones(len(normal), bool)
    except np.linalg.LinAlgError:
        step, solved = np.zeros((len(normal), 6)), np.ones(len(normal), bool)
        for b in range(len(normal)):
            try:
                step[b] = np.linalg.solve(damped[b], gradient[b])[:, 0]
            except np.linalg.LinAlgError:
                solved[b] = False
        return step, solved


def pose_covariance(J: np.ndarray, sigma_px: float) -> np.ndarray:
    """(6, 6) covariance ``sigma^2 (J^T J)^-1`` of ``delta = (tx, ty, tz, rx, ry, rz)`` (child frame,
    metres and radians) from the (2N, 6) residual Jacobian and the per-axis pixel noise ``sigma_px``.

    Raises DegenerateError when ``J^T J`` is (numerically) singular.
    """
    J = np.asarray(J, dtype=np.float64)
    covariance, regular = pose_covariances((J.T @ J)[None], sigma_px)
    if not regular[0]:
        raise DegenerateError("the measurements do not constrain all six pose parameters")
    return covariance[0]


def pose_covariances(normal: np.ndarray, sigma_px: float) -> tuple[np.ndarray, np.ndarray]:
    """``(covariance, regular)``: (B, 6, 6) ``sigma^2 (J^T J)^-1`` (as ``pose_covariance``) of (B, 6, 6)
    ``J^T J`` (``RefineResults.normal``), and (B,) whether each ``J^T J`` is regular (its smallest
    eigenvalue above 1e-12 times its largest); a singular one's covariance is NaN."""
    normal = np.asarray(normal, dtype=np.float64)
    eigenvalues = np.linalg.eigvalsh(normal)
    regular = eigenvalues[:, 0] > 1e-12 * eigenvalues[:, -1]
    covariance = np.full(normal.shape, np.nan)
    if np.any(regular):
        inverse = sigma_px**2 * np.linalg.inv(normal[regular])
        covariance[regular] = (inverse + inverse.transpose(0, 2, 1)) / 2
    return covariance, regular
