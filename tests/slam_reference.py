"""The SLAM optimisation's cost minimised by scipy, as an independent reference for pycolmap's bundle adjuster.

Same cost as ``services.slam.optimisation`` (its module docstring): per observation the whitened
error ``e / sigma`` (2,) under Ceres's Huber loss of its squared norm ``s``, summed as
``0.5 * sum(rho(s))``. ``scipy.optimize.least_squares(loss="huber")`` would not be that cost: scipy
applies its loss to each scalar residual, so u and v would bend separately. The reference instead
gives scipy, with ``loss="linear"``, the rescaled residual ``sqrt(rho(s) / s) * e / sigma`` whose
squared norm is ``rho(s)``. Parameters: each free keyframe's rotation vector and translation of
``T_camera_world``, and each point seen at least twice (a point seen once constrains nothing and
pycolmap leaves it out: so does the reference). The Jacobian is by finite differences with its
sparsity pattern given (``jac_sparsity``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import lil_matrix

from services.geometry.rotation import matrix_from_rotvec, rotvec_from_matrix
from services.slam.optimisation import HUBER_PX, BundleProblem


@dataclass(frozen=True)
class ReferenceResult:
    """``poses`` and ``points`` as ``BundleResult``'s; ``cost``: the final ``0.5 * sum(rho)``;
    ``evaluations``: scipy's function evaluations."""

    poses: dict[int, np.ndarray]
    points: dict[int, np.ndarray]
    cost: float
    evaluations: int


def huber(s: np.ndarray, huber_px: float) -> np.ndarray:
    """Ceres's Huber loss ``rho(s)`` of squared norms ``s``: ``s`` up to ``h^2``, ``2 h sqrt(s) - h^2`` beyond
    (``h = huber_px``)."""
    return np.where(s <= huber_px ** 2, s, 2 * huber_px * np.sqrt(s) - huber_px ** 2)


def robust_cost(problem: BundleProblem, poses: dict[int, np.ndarray], points: dict[int, np.ndarray],
                huber_px: float = HUBER_PX) -> float:
    """``0.5 * sum(rho)`` over the observations of points seen at least twice, at ``poses`` and ``points``."""
    keep = _kept(problem)
    sigmas = np.ones(len(problem.pixels)) if problem.sigmas is None else np.asarray(problem.sigmas)
    T = np.stack([poses[int(k)] for k in problem.frame_ids[keep]])
    X = np.stack([points[int(i)] for i in problem.point_ids[keep]])
    camera = np.einsum("mij,mj->mi", T[:, :3, :3], X) + T[:, :3, 3]
    e = (_project(problem.K, camera) - problem.pixels[keep]) / sigmas[keep, None]
    return float(0.5 * np.sum(huber(np.sum(e * e, axis=1), huber_px)))


def _kept(problem: BundleProblem) -> np.ndarray:
    """(M,) bool: the observation's point is seen at least twice."""
    _, inverse, counts = np.unique(problem.point_ids, return_inverse=True, return_counts=True)
    return counts[inverse] >= 2


def _project(K: np.ndarray, camera: np.ndarray) -> np.ndarray:
    return camera[:, :2] / camera[:, 2:] * K[[0, 1], [0, 1]] + K[:2, 2]


def robust_residuals(K: np.ndarray, T: np.ndarray, points: np.ndarray, pixels: np.ndarray, sigmas: np.ndarray,
                     huber_px: float) -> np.ndarray:
    """(2M,) rescaled whitened errors ``sqrt(rho(s) / s) * e / sigma`` of M observations: per-observation
    poses (M, 4, 4), points (M, 3), pixels (M, 2), sigmas (M,)."""
    camera = np.einsum("mij,mj->mi", T[:, :3, :3], points) + T[:, :3, 3]
    e = (_project(K, camera) - pixels) / sigmas[:, None]
    s = np.sum(e * e, axis=1)
    scale = np.sqrt(huber(s, huber_px) / np.maximum(s, 1e-300))
    return (e * np.where(s > 0, scale, 1.0)[:, None]).ravel()


def reference_refine_pose(K: np.ndarray, T_camera_world: np.ndarray, points: np.ndarray, pixels: np.ndarray,
                          sigmas: np.ndarray, huber_px: float = HUBER_PX) -> np.ndarray:
    """(4, 4) pose minimising the module's cost over one pose (rotation vector and translation) with
    the (N, 3) points fixed, from ``T_camera_world``."""
    def pose(x: np.ndarray) -> np.ndarray:
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = matrix_from_rotvec(x[:3]), x[3:]
        return T

    def residuals(x: np.ndarray) -> np.ndarray:
        return robust_residuals(K, np.broadcast_to(pose(x), (len(points), 4, 4)), points, pixels, sigmas, huber_px)

    x0 = np.concatenate([rotvec_from_matrix(T_camera_world[:3, :3]), T_camera_world[:3, 3]])
    return pose(least_squares(residuals, x0, method="trf", x_scale="jac", ftol=1e-12, xtol=1e-12, gtol=1e-12).x)


def reference_bundle_adjust(problem: BundleProblem, huber_px: float = HUBER_PX,
                            tolerance: float = 1e-12) -> ReferenceResult:
    """Minimise the module's cost over the free poses and the points seen twice or more, from the
    problem's start, by ``least_squares`` (trust region reflective, ``x_scale="jac"``)."""
    keep = _kept(problem)
    frame_ids, point_ids = problem.frame_ids[keep], problem.point_ids[keep]
    pixels = problem.pixels[keep]
    sigmas = (np.ones(len(problem.pixels)) if problem.sigmas is None else np.asarray(problem.sigmas))[keep]
    free = sorted(set(np.unique(frame_ids).tolist()) - problem.fixed)
    moving = np.unique(point_ids)
    pose_slot = {k: i for i, k in enumerate(free)}
    frame_slot = np.array([pose_slot.get(int(k), -1) for k in frame_ids])
    point_slot = np.searchsorted(moving, point_ids)
    fixed_T = np.stack([problem.poses[int(k)] for k in frame_ids])
    offset = 6 * len(free)

    def unpack(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        T = fixed_T.copy()
        R = np.stack([matrix_from_rotvec(x[6 * i:6 * i + 3]) for i in range(len(free))]) if free else None
        on_free = frame_slot >= 0
        if R is not None:
            T[on_free, :3, :3] = R[frame_slot[on_free]]
            T[on_free, :3, 3] = x[:offset].reshape(-1, 6)[frame_slot[on_free], 3:]
        return T, x[offset:].reshape(-1, 3)

    def residuals(x: np.ndarray) -> np.ndarray:
        T, X = unpack(x)
        return robust_residuals(problem.K, T, X[point_slot], pixels, sigmas, huber_px)

    sparsity = lil_matrix((2 * len(pixels), offset + 3 * len(moving)), dtype=np.int8)
    rows = np.arange(len(pixels))
    for axis in range(2):
        for column in range(3):
            sparsity[2 * rows + axis, offset + 3 * point_slot + column] = 1
        on_free = frame_slot >= 0
        for column in range(6):
            sparsity[2 * rows[on_free] + axis, 6 * frame_slot[on_free] + column] = 1
    x0 = np.concatenate([np.concatenate([rotvec_from_matrix(problem.poses[k][:3, :3]), problem.poses[k][:3, 3]])
                         for k in free] + [np.stack([problem.points[int(i)] for i in moving]).ravel()])
    solution = least_squares(residuals, x0, jac_sparsity=sparsity, method="trf", x_scale="jac", loss="linear",
                             ftol=tolerance, xtol=tolerance, gtol=tolerance)
    poses = {k: np.asarray(T, dtype=np.float64).copy() for k, T in problem.poses.items()}
    for k in free:
        i = pose_slot[k]
        poses[k][:3, :3] = matrix_from_rotvec(solution.x[6 * i:6 * i + 3])
        poses[k][:3, 3] = solution.x[6 * i + 3:6 * i + 6]
    points = {k: np.asarray(X, dtype=np.float64).copy() for k, X in problem.points.items()}
    for i, point in enumerate(moving.tolist()):
        points[point] = solution.x[offset + 3 * i:offset + 3 * i + 3].copy()
    return ReferenceResult(poses, points, float(solution.cost), int(solution.nfev))
