"""Compiled fits of labelled bodies: the per-instant loop of ``rigid.fit_labelled`` in machine code (``numba``).

Per body, with its spheres (body frame) labelled with points (world frame): while at least ``min_spheres``
spheres are labelled and not on one line, the least-squares rigid transform (the SVD of the cross-covariance,
its reflection removed: ``absolute_orientation.least_squares_transforms``) is fitted; a fit whose residual RMS
breaks its gate (``gate_rms``, and on three spheres ``three_turn_rad`` times their ``rigid.width``) lets go the
sphere whose absence leaves the smallest residual RMS (with three, the first) and is made again. A fit kept
gets the sandwich covariance of ``absolute_orientation.pose_covariances`` from its points' covariances. For
the few bodies of an instant NumPy's batches cost more in calls than in arithmetic; here the arithmetic alone.
Cached on disk beside this module (``cache=True``).
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["fit_bodies", "warm"]


@njit(cache=True, nogil=True)
def _fit(spheres: np.ndarray, world: np.ndarray, used: np.ndarray) -> tuple[np.ndarray, float]:
    """``(T_world_body (4, 4), residual RMS m)`` of the (N, 3) ``spheres`` onto their (N, 3) ``world`` points,
    over the (N,) bool ``used`` ones."""
    count = 0.0
    mu_body = np.zeros(3)
    mu_world = np.zeros(3)
    for n in range(len(used)):
        if used[n]:
            count += 1.0
            mu_body += spheres[n]
            mu_world += world[n]
    mu_body /= count
    mu_world /= count
    H = np.zeros((3, 3))
    for n in range(len(used)):
        if used[n]:
            H += np.outer(world[n] - mu_world, spheres[n] - mu_body)
    U, _, Vt = np.linalg.svd(H / count)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0.0:
        U[:, 2] = -U[:, 2]
    R = U @ Vt
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = mu_world - R @ mu_body
    total = 0.0
    for n in range(len(used)):
        if used[n]:
            total += np.sum((world[n] - (R @ spheres[n] + T[:3, 3])) ** 2)
    return T, np.sqrt(total / count)


@njit(cache=True, nogil=True)
def _collinear(spheres: np.ndarray, used: np.ndarray, tolerance: float) -> bool:
    """Whether the ``used`` of (N, 3) ``spheres`` lie on one line (centred singular values' ratio)."""
    count = 0.0
    mean = np.zeros(3)
    for n in range(len(used)):
        if used[n]:
            count += 1.0
            mean += spheres[n]
    mean /= max(count, 1.0)
    centred = np.zeros((len(used), 3))
    for n in range(len(used)):
        if used[n]:
            centred[n] = spheres[n] - mean
    spread = np.linalg.svd(centred)[1]
    return spread[1] <= tolerance * max(spread[0], 1e-300)


@njit(cache=True, nogil=True)
def _width(spheres: np.ndarray, used: np.ndarray) -> float:
    """The farthest a ``used`` sphere lies from the line through the two used spheres farthest apart."""
    first, second, apart = 0, 0, -1.0
    for i in range(len(used)):
        for j in range(len(used)):
            if used[i] and used[j]:
                distance = np.sqrt(np.sum((spheres[i] - spheres[j]) ** 2))
                if distance > apart:
                    first, second, apart = i, j, distance
    direction = spheres[second] - spheres[first]
    direction /= np.sqrt(np.sum(direction**2))
    widest = 0.0
    for n in range(len(used)):
        if used[n]:
            offset = spheres[n] - spheres[first]
            across = offset - np.sum(offset * direction) * direction
            widest = max(widest, np.sqrt(np.sum(across**2)))
    return widest


@njit(cache=True, nogil=True)
def _covariance(T: np.ndarray, spheres: np.ndarray, sigma: np.ndarray, used: np.ndarray) -> np.ndarray:
    """(6, 6) ``H^-1 (sum_i J_i^T Sigma_i J_i) H^-1`` (``absolute_orientation.pose_covariance``) over the
    ``used`` spheres, ``sigma`` (N, 3, 3) their points' covariances."""
    H = np.zeros((6, 6))
    B = np.zeros((6, 6))
    J = np.zeros((3, 6))
    R = np.ascontiguousarray(T[:3, :3])
    for n in range(len(used)):
        if not used[n]:
            continue
        rotated = R @ spheres[n]
        x, y, z = rotated[0], rotated[1], rotated[2]
        J[:, :] = 0.0
        J[0, 1], J[0, 2] = z, -y
        J[1, 0], J[1, 2] = -z, x
        J[2, 0], J[2, 1] = y, -x
        J[0, 3] = J[1, 4] = J[2, 5] = 1.0
        H += J.T @ J
        B += J.T @ sigma[n] @ J
    H_inv = np.linalg.inv(H)
    covariance = H_inv @ B @ H_inv
    return (covariance + covariance.T) / 2


@njit(cache=True, nogil=True)
def _fit_bodies(spheres: np.ndarray, sizes: np.ndarray, labels: np.ndarray, points: np.ndarray,
                covariances: np.ndarray, with_covariances: bool, gate_rms: float, three_turn_rad: float,
                min_spheres: int, collinear_tolerance: float
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    bodies, widest = labels.shape
    fitted = np.zeros(bodies, np.bool_)
    transforms = np.zeros((bodies, 4, 4))
    rms = np.zeros(bodies)
    indices = labels.copy()
    pose_covariances = np.full((bodies, 6, 6), np.nan)
    world = np.zeros((widest, 3))
    for b in range(bodies):
        size = sizes[b]
        mine = spheres[b, :size]
        while True:
            used = indices[b, :size] >= 0
            if np.sum(used) < min_spheres or _collinear(mine, used, collinear_tolerance):
                break
            for n in range(size):
                if used[n]:
                    world[n] = points[indices[b, n]]
            T, error = _fit(mine, world[:size], used)
            gate = min(gate_rms, three_turn_rad * _width(mine, used)) if np.sum(used) == 3 else gate_rms
            if error <= gate:
                fitted[b], transforms[b], rms[b] = True, T, error
                if with_covariances:
                    sigma = np.zeros((size, 3, 3))
                    for n in range(size):
                        if used[n]:
                            sigma[n] = covariances[indices[b, n]]
                    pose_covariances[b] = _covariance(T, mine, sigma, used)
                break
            outlier, best = -1, np.inf
            for n in range(size):
                if not used[n]:
                    continue
                if np.sum(used) <= 3:
                    outlier = n
                    break
                subset = used.copy()
                subset[n] = False
                if _collinear(mine, subset, collinear_tolerance):
                    continue
                left = _fit(mine, world[:size], subset)[1]
                if left < best:
                    outlier, best = n, left
            indices[b, outlier if outlier >= 0 else np.argmax(used)] = -1
    return fitted, transforms, rms, indices, pose_covariances


def fit_bodies(spheres: np.ndarray, sizes: np.ndarray, labels: np.ndarray, points: np.ndarray,
               covariances: np.ndarray | None, gate_rms: float, three_turn_rad: float, min_spheres: int,
               collinear_tolerance: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(fitted (B,) bool, T_world_body (B, 4, 4), residual RMS (B,) m, labels (B, N) int64 after the spheres let
    go, covariances (B, 6, 6), NaN without point covariances)`` of B bodies (see the module docstring).

    ``spheres``: (B, N, 3) body frame, body b's first ``sizes[b]`` rows; ``labels``: (B, N) int64 point index
    per sphere (-1: none); ``points``: (M, 3) world frame; ``covariances``: (M, 3, 3) m^2 or None. Shapes are not
    checked.
    """
    with_covariances = covariances is not None
    sigma = np.ascontiguousarray(covariances, np.float64) if covariances is not None else np.zeros((1, 3, 3))
    return _fit_bodies(np.ascontiguousarray(spheres, np.float64), np.ascontiguousarray(sizes, np.int64),
                       np.ascontiguousarray(labels, np.int64), np.ascontiguousarray(points, np.float64).reshape(-1, 3),
                       sigma, with_covariances, float(gate_rms), float(three_turn_rad), int(min_spheres),
                       float(collinear_tolerance))


def warm() -> None:
    """Compile ``fit_bodies`` (or load it from the disk cache) on one body of four spheres."""
    spheres = np.array([[[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.08, 0.0], [0.05, 0.05, 0.03]]])
    fit_bodies(spheres, np.array([4]), np.arange(4)[None], spheres[0] + 1.0, np.tile(np.eye(3) * 1e-8, (4, 1, 1)),
               0.001, 0.017, 3, 1e-9)
