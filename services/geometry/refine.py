"""Levenberg-Marquardt refinement of camera-object poses by reprojection error, and their covariance.

A pose is ``T_camera_object`` (4, 4): it maps (N, 3) object points (object frame, metres)
into the camera frame, where a distortion-free pinhole ``K`` (3, 3, last row (0, 0, 1))
projects them to (N, 2) pixels. Undistort observed pixels first (``cv2.undistortPoints(..., P=K)``).

Updates are right perturbations in the object (child) frame, ``T <- T @ D(delta)`` with
``delta = (tx, ty, tz, rx, ry, rz)`` (metres, then a rotation vector in radians) and the
simple increment ``D(delta) = [R(r) | t]`` rather than the full SE(3) exponential. Both agree
to first order, so the Jacobian at ``delta = 0`` and the covariance built from it are those of
the perturbation ``protocol.poses.Pose.covariance`` documents.

Speed: the problems of a frame are tiny (a marker has 4 points), so numpy's per-call overhead,
not arithmetic, sets the cost. ``refine_poses`` therefore advances B problems together: each
pass solves all their damped normal equations in one call and evaluates all their candidate
poses (residuals, Jacobians, normal equations) in a handful of calls, while each problem keeps
its own damping and stopping test in plain Python. A rejected step leaves a problem's pose and
normal equations as they were, so after one the problem tries its next ``LADDER`` dampings in
the same pass and the walk through them stops where it would have stopped step by step: every
problem takes exactly the steps it takes alone (``refine_pose``, the one-problem case).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from services.geometry.homography import DegenerateError
from services.geometry.shapes import check_shape

INITIAL_DAMPING = 1e-3
MIN_DAMPING = 1e-12
MAX_DAMPING = 1e12
LADDER = 6
"""Dampings a problem tries in one pass after a rejected step. At the optimum, where rounding noise
decides, rejections come in short streaks: the first rejection and one pass of ``LADDER`` cover nearly
all of them on the ``markers`` scene."""
SKEW = np.array([[[0, 0, 0], [0, 0, -1], [0, 1, 0]],
                 [[0, 0, 1], [0, 0, 0], [-1, 0, 0]],
                 [[0, -1, 0], [1, 0, 0], [0, 0, 0]]], dtype=np.float64).reshape(3, 9)
"""``w @ SKEW`` is the cross-product matrix ``[w]x`` of (..., 3) vectors, flattened to (..., 9)."""
DAMPED_DIAGONAL = np.eye(6)


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
    """B refinements: ``T`` (B, 4, 4), ``rms_px`` (B,), ``iterations`` (B,) int and ``converged`` (B,) bool
    as in ``RefineResult``; ``normal``: (B, 6, 6) ``J^T J`` at ``T`` (for ``pose_covariances``);
    ``degenerate``: (B,) bool, the damped normal equations turned singular (the points do not
    constrain all six pose parameters): that problem stopped there, not converged, at its last
    accepted pose."""

    T: np.ndarray
    rms_px: np.ndarray
    iterations: np.ndarray
    normal: np.ndarray
    converged: np.ndarray
    degenerate: np.ndarray


def residuals_and_jacobian(T: np.ndarray, points_obj: np.ndarray, pixels: np.ndarray,
                           K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(r, J)``: (2N,) residuals ``project(T @ X) - pixels`` and their (2N, 6) analytic Jacobian.

    ``points_obj``: (N, 3) object frame; ``pixels``: (N, 2); ``K``: (3, 3). Points need z > 0.
    The one-pose case of ``residuals_and_jacobians``.
    """
    points_obj = check_shape(points_obj, "N,3", "points_obj", np.float64)
    r, J = residuals_and_jacobians(check_shape(T, "4,4", "T", np.float64)[None], points_obj[None],
                                   check_shape(pixels, f"{len(points_obj)},2", "pixels", np.float64)[None], K)
    return r[0], J[0]


def residuals_and_jacobians(T: np.ndarray, points_obj: np.ndarray, pixels: np.ndarray,
                            K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(r, J)`` of B poses ``T_camera_object`` (B, 4, 4), each with its own (B, N, 3) ``points_obj``
    (object frame) and (B, N, 2) ``pixels``: (B, 2N) residuals ``project(T @ X) - pixels``
    (u0, v0, u1, v1, ...) and their (B, 2N, 6) Jacobians with respect to ``delta``. Points need z > 0.
    """
    T, K = check_shape(T, "B,4,4", "T", np.float64), check_shape(K, "3,3", "K", np.float64)
    points_obj = check_shape(points_obj, f"{len(T)},N,3", "points_obj")
    pixels = check_shape(pixels, f"{len(T)},{points_obj.shape[1]},2", "pixels")
    augmented, _ = augmented_rows(T, point_basis(points_obj), pixels, K)
    flat = augmented.reshape(len(augmented), -1, 7)
    return -flat[..., 6], flat[..., :6].copy()


def point_basis(points_obj: np.ndarray) -> np.ndarray:
    """(B, N, 4, 7) per point ``[[I, -[X]x, X], [0, 0, 1]]`` of (B, N, 3) points ``X``: a pose ``T`` times
    it holds the derivative of ``T D(delta) X`` at ``delta = 0`` (6 columns) and ``T X`` (the last)."""
    points_obj = np.asarray(points_obj, dtype=np.float64)
    basis = np.zeros((*points_obj.shape[:2], 4, 7))
    basis[..., :3, :3] = np.eye(3)
    basis[..., :3, 3:6] = -(points_obj @ SKEW).reshape(*points_obj.shape[:2], 3, 3)
    basis[..., :3, 6] = points_obj
    basis[..., 3, 6] = 1.0
    return basis


def augmented_rows(T: np.ndarray, basis: np.ndarray, pixels: np.ndarray,
                   K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(A, front)`` of B poses (B, 4, 4), their points' (B, N, 4, 7) ``point_basis`` and (B, N, 2) ``pixels``.

    ``A``: (B, N, 2, 7), per point and pixel axis the Jacobian row of the residual and then the
    negated residual, so that reshaped to (B, 2N, 7) it is ``[J | -r]``. ``front``: (B,) every
    point has z > 0 (where one has not, that pose's ``A`` is meaningless). Per point, ``K T basis``
    holds ``dq/ddelta = K R [I, -[X]x]`` and ``q = K T X``, the pixel ``u`` times the depth
    ``z = q[2]``, so the derivative of ``u = q[:2] / z`` is ``(dq[:2] - u dq[2]) / z``.
    """
    G = (K @ T[:, :3])[:, None] @ basis
    positive = G[..., 2, 6] > 0
    G *= (1.0 / np.where(positive, G[..., 2, 6], 1.0))[..., None, None]
    projected = G[..., :2, 6]
    augmented = np.empty((*positive.shape, 2, 7))
    np.subtract(G[..., :2, :6], projected[..., None] * G[..., 2:3, :6], out=augmented[..., :6])
    np.subtract(pixels, projected, out=augmented[..., 6])
    return augmented, positive.all(axis=1)


def normal_equations(augmented: np.ndarray) -> np.ndarray:
    """(B, 7, 7) ``[J | -r]^T [J | -r]`` of (B, N, 2, 7) ``augmented_rows``: ``J^T J`` (6, 6), ``-J^T r``
    (the last column) and the cost ``r^T r`` (the corner)."""
    flat = augmented.reshape(len(augmented), -1, 7)
    return flat.transpose(0, 2, 1) @ flat


def refine_pose(T: np.ndarray, points_obj: np.ndarray, pixels: np.ndarray, K: np.ndarray,
                max_iterations: int = 100, tolerance: float = 1e-10) -> RefineResult:
    """Refine ``T_camera_object`` (4, 4) to minimise the reprojection error of (N, 3) ``points_obj``
    (object frame) against (N, 2) undistorted ``pixels`` under the pinhole ``K``; N >= 3.

    The method is ``refine_poses``'s. Raises ValueError when a point lies behind the camera at
    the start, DegenerateError when the points do not constrain the pose (e.g. all at one point).
    """
    points_obj = check_shape(points_obj, "N,3", "points_obj", np.float64)
    pixels = check_shape(pixels, "N,2", "pixels", np.float64)
    result = refine_poses(check_shape(T, "4,4", "T", np.float64)[None], points_obj[None], pixels[None], K,
                          max_iterations, tolerance)
    if result.degenerate[0]:
        raise DegenerateError("the points do not constrain all six pose parameters")
    return RefineResult(result.T[0], float(result.rms_px[0]), int(result.iterations[0]),
                        residuals_and_jacobian(result.T[0], points_obj, pixels, K)[1], bool(result.converged[0]))


def refine_poses(T: np.ndarray, points_obj: np.ndarray, pixels: np.ndarray, K: np.ndarray,
                 max_iterations: int = 100, tolerance: float = 1e-10) -> RefineResults:
    """Refine B >= 1 poses ``T_camera_object`` (B, 4, 4), each against its own (B, N, 3) ``points_obj``
    (object frame) and (B, N, 2) undistorted ``pixels``, under one pinhole ``K``; N >= 3.

    Per problem: Marquardt's damping (``lambda * diag(J^T J)``, so the metre and radian columns
    need no common scale), lambda divided by 10 on an accepted step and multiplied by 10 on a
    rejected one; a step that puts a point behind the camera is rejected. Stops when a step
    changes the cost by less than ``tolerance`` relatively, when the step is below ``tolerance``
    (metres / radians), when lambda has grown beyond any useful step, or (``degenerate``) when
    the damped normal equations are singular. The problems advance together (module docstring).
    Raises ValueError when a point lies behind the camera at a start, DegenerateError unless
    the shapes give N >= 3 points.
    """
    T = np.array(check_shape(T, "*,4,4", "T"), dtype=np.float64).reshape(-1, 4, 4)
    count = len(T)
    pixels = np.asarray(pixels, dtype=np.float64).reshape(count, -1, 2)
    basis = point_basis(np.asarray(points_obj, dtype=np.float64).reshape(count, -1, 3))
    n = basis.shape[1]
    if pixels.shape[1] != n or n < 3:
        raise DegenerateError(f"need N >= 3 matching points, got {n} and {pixels.shape[1]}")
    K = check_shape(K, "3,3", "K", np.float64)
    augmented, front = augmented_rows(T, basis, pixels, K)
    if not np.all(front):
        raise ValueError("a point lies behind the camera at the initial pose")
    normal = normal_equations(augmented)
    damping, iterations, rungs = [INITIAL_DAMPING] * count, [0] * count, [1] * count
    converged, degenerate = [False] * count, [False] * count
    running = list(range(count)) if max_iterations > 0 else []
    while running:
        owners, dampings, tries = [], [], []
        for b in running:
            tries.append(min(rungs[b], max_iterations - iterations[b]))
            owners += [b] * tries[-1]
            rung_damping = damping[b]
            for _ in range(tries[-1]):
                dampings.append(rung_damping)
                rung_damping *= 10
        picks = np.array(owners)
        steps, singular = damped_steps(normal.take(picks, axis=0), np.array(dampings))
        candidate = T.take(picks, axis=0) @ increments(steps)
        candidate_rows, front = augmented_rows(candidate, basis.take(picks, axis=0), pixels.take(picks, axis=0), K)
        candidate_normal = normal_equations(candidate_rows)
        step_sizes, costs, fronts = np.abs(steps).max(axis=1).tolist(), candidate_normal[:, 6, 6].tolist(), \
            front.tolist()
        current, taken, accepted, still, first = normal[:, 6, 6].tolist(), [], [], [], 0
        for b, tried in zip(running, tries, strict=True):
            done = False
            for k in range(first, first + tried):
                iterations[b] += 1
                if k in singular:
                    degenerate[b] = done = True
                    break
                cost, candidate_cost = current[b], costs[k] if fronts[k] else math.inf
                done = step_sizes[k] < tolerance
                if candidate_cost <= cost:
                    done = done or cost - candidate_cost <= tolerance * cost
                    taken.append(k)
                    accepted.append(b)
                    damping[b], rungs[b] = max(damping[b] / 10, MIN_DAMPING), 1
                    break
                damping[b], rungs[b] = damping[b] * 10, LADDER
                done = done or damping[b] > MAX_DAMPING
                if done:
                    break
            first += tried
            converged[b] = done and not degenerate[b]
            if not done and iterations[b] < max_iterations:
                still.append(b)
        if accepted:
            T[accepted], normal[accepted] = candidate.take(taken, axis=0), candidate_normal.take(taken, axis=0)
        running = still
    return RefineResults(T, np.sqrt(normal[:, 6, 6] / n), np.array(iterations), normal[:, :6, :6].copy(),
                         np.array(converged), np.array(degenerate))


def increments(steps: np.ndarray) -> np.ndarray:
    """(R, 4, 4) ``D(delta) = [R(r) | t]`` of (R, 6) steps ``delta = (t, r)``, ``R(r)`` by cv2.Rodrigues
    (one call a step costs less than Rodrigues' formula spelt out in numpy for these sizes)."""
    D = np.empty((len(steps), 4, 4))
    D[:, 3] = (0.0, 0.0, 0.0, 1.0)
    D[:, :3, 3] = steps[:, :3]
    D[:, :3, :3] = [cv2.Rodrigues(rotvec)[0] for rotvec in steps[:, 3:, None]]
    return D


def damped_steps(normal: np.ndarray, damping: np.ndarray) -> tuple[np.ndarray, set[int]]:
    """``(steps, singular)``: (R, 6) solutions of ``(J^T J + lambda diag(J^T J)) step = -J^T r`` from (R, 7, 7)
    ``normal_equations`` and (R,) ``damping`` lambda, and the rows whose system is singular (their
    step is zero)."""
    damped = normal[:, :6, :6] * (1 + damping[:, None, None] * DAMPED_DIAGONAL)
    gradient = normal[:, :6, 6:]
    try:
        return np.linalg.solve(damped, gradient)[..., 0], set()
    except np.linalg.LinAlgError:
        steps, singular = np.zeros((len(normal), 6)), set()
        for k in range(len(normal)):
            try:
                steps[k] = np.linalg.solve(damped[k], gradient[k])[:, 0]
            except np.linalg.LinAlgError:
                singular.add(k)
        return steps, singular


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
    ``J^T J`` (e.g. ``RefineResults.normal``), and (B,) whether each ``J^T J`` is regular (its smallest
    eigenvalue above 1e-12 times its largest); a singular one's covariance is NaN."""
    normal = np.asarray(normal, dtype=np.float64)
    eigenvalues = np.linalg.eigvalsh(normal)
    regular = eigenvalues[:, 0] > 1e-12 * eigenvalues[:, -1]
    inverse = np.linalg.inv(np.where(regular[:, None, None], normal, np.eye(6)))
    covariance = (inverse + inverse.transpose(0, 2, 1)) * (sigma_px**2 / 2)
    covariance[~regular] = np.nan
    return covariance, regular
