"""Compiled triangulation of N points, each from its own subset of C calibrated cameras.

The method of ``services.geometry.triangulation.triangulate_many``, one point at a time in a loop that
``numba`` compiles to machine code: a DLT over the views on ideal pinhole pixels (each view's two rows
scaled to unit norm, the right singular vector of least singular value), Gauss-Newton on the reprojection
error through plumb_bob distortion (``services.geometry.camera_stack``'s model, written out), and the
covariance ``(J^T J)^+ sigma_px^2`` (the 3x3 systems in closed form, by the adjugate). For the few points
of one instant of a motion-capture rig a NumPy batch costs more in calls than in arithmetic; here it costs
the arithmetic alone. The compiled code is cached on disk beside this module (``cache=True``), so a process
after the first loads it in milliseconds.

World = the cameras' common frame; pixels in px, points in m.
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["project_point", "triangulate_points"]


@njit(cache=True, nogil=True)
def project_point(K: np.ndarray, dist: np.ndarray, R: np.ndarray, t: np.ndarray, c: int, X: np.ndarray,
             pixel: np.ndarray, jacobian: np.ndarray) -> None:
    """Camera c's observed pixel (2,) of world point X (3,), and its derivative (2, 3) px/m, written in place."""
    p0 = R[c, 0, 0] * X[0] + R[c, 0, 1] * X[1] + R[c, 0, 2] * X[2] + t[c, 0]
    p1 = R[c, 1, 0] * X[0] + R[c, 1, 1] * X[1] + R[c, 1, 2] * X[2] + t[c, 1]
    p2 = R[c, 2, 0] * X[0] + R[c, 2, 1] * X[1] + R[c, 2, 2] * X[2] + t[c, 2]
    inverse_z = 1.0 / p2
    x, y = p0 * inverse_z, p1 * inverse_z
    k1, k2, q1, q2, k3 = dist[c, 0], dist[c, 1], dist[c, 2], dist[c, 3], dist[c, 4]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xy = x * y
    xd = x * radial + 2.0 * q1 * xy + q2 * (r2 + 2.0 * x * x)
    yd = y * radial + q1 * (r2 + 2.0 * y * y) + 2.0 * q2 * xy
    fx, fy = K[c, 0, 0], K[c, 1, 1]
    pixel[0] = fx * xd + K[c, 0, 2]
    pixel[1] = fy * yd + K[c, 1, 2]
    d_radial = k1 + r2 * (2.0 * k2 + 3.0 * r2 * k3)
    cross = 2.0 * xy * d_radial + 2.0 * q1 * x + 2.0 * q2 * y
    a00 = fx * (radial + 2.0 * x * x * d_radial + 2.0 * q1 * y + 6.0 * q2 * x)
    a01 = fx * cross
    a10 = fy * cross
    a11 = fy * (radial + 2.0 * y * y * d_radial + 6.0 * q1 * y + 2.0 * q2 * x)
    for j in range(3):
        n0 = inverse_z * R[c, 0, j] - x * inverse_z * R[c, 2, j]
        n1 = inverse_z * R[c, 1, j] - y * inverse_z * R[c, 2, j]
        jacobian[0, j] = a00 * n0 + a01 * n1
        jacobian[1, j] = a10 * n0 + a11 * n1


@njit(cache=True, nogil=True)
def _evaluate(K: np.ndarray, dist: np.ndarray, R: np.ndarray, t: np.ndarray, pixels: np.ndarray, seen: np.ndarray,
              X: np.ndarray, residuals: np.ndarray, J: np.ndarray) -> float:
    """Residuals (C, 2) observed - projected and their derivatives J (2C, 3) at X, zero where unseen, in place;
    returns the sum of squared residuals."""
    pixel = np.empty(2)
    jacobian = np.empty((2, 3))
    total = 0.0
    for c in range(len(seen)):
        if not seen[c]:
            residuals[c, 0] = residuals[c, 1] = 0.0
            J[2 * c, :] = 0.0
            J[2 * c + 1, :] = 0.0
            continue
        project_point(K, dist, R, t, c, X, pixel, jacobian)
        for k in range(2):
            residuals[c, k] = pixels[c, k] - pixel[k]
            total += residuals[c, k] ** 2
            for j in range(3):
                J[2 * c + k, j] = -jacobian[k, j]
    return total


@njit(cache=True, nogil=True)
def _normal(J: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(J^T J (3, 3), J^T r (3,))`` of J (M, 3) and r (M,), summed row by row (no BLAS call for a few rows)."""
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for m in range(J.shape[0]):
        for i in range(3):
            b[i] += J[m, i] * r[m]
            for j in range(i, 3):
                A[i, j] += J[m, i] * J[m, j]
    for i in range(3):
        for j in range(i):
            A[i, j] = A[j, i]
    return A, b


@njit(cache=True, nogil=True)
def _inverse(A: np.ndarray) -> np.ndarray:
    """The inverse of the symmetric (3, 3) ``A`` by its adjugate, or its pseudo-inverse (``np.linalg.pinv``) when
    its determinant is under 1e-12 of the product of its diagonal (singular to working precision)."""
    adjugate = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            i1, i2 = (j + 1) % 3, (j + 2) % 3
            j1, j2 = (i + 1) % 3, (i + 2) % 3
            adjugate[i, j] = A[i1, j1] * A[i2, j2] - A[i1, j2] * A[i2, j1]
    determinant = A[0, 0] * adjugate[0, 0] + A[0, 1] * adjugate[1, 0] + A[0, 2] * adjugate[2, 0]
    if not abs(determinant) > 1e-12 * abs(A[0, 0] * A[1, 1] * A[2, 2]):
        return np.ascontiguousarray(np.linalg.pinv(A))
    return adjugate / determinant


@njit(cache=True, nogil=True)
def _dlt(projections: np.ndarray, ideal: np.ndarray, seen: np.ndarray) -> np.ndarray:
    """(3,) DLT point of one point's ideal pixels (C, 2) in the cameras it is ``seen`` (C,) in; NaN at infinity."""
    cameras = len(seen)
    rows = np.zeros((2 * cameras, 4))
    views = 0
    for c in range(cameras):
        if not seen[c]:
            continue
        views += 1
        for k in range(2):
            norm = 0.0
            for j in range(4):
                rows[2 * c + k, j] = ideal[c, k] * projections[c, 2, j] - projections[c, k, j]
                norm += rows[2 * c + k, j] ** 2
            rows[2 * c + k, :] /= max(np.sqrt(norm), 1e-300)
    X = np.linalg.svd(rows)[2][3]
    point = np.full(3, np.nan)
    if views >= 2 and abs(X[3]) >= 1e-12 * np.sqrt(np.sum(X**2)):
        point[:] = X[:3] / X[3]
    return point


def triangulate_points(K: np.ndarray, dist: np.ndarray, R: np.ndarray, t: np.ndarray, projections: np.ndarray,
                       pixels: np.ndarray, ideal: np.ndarray, seen: np.ndarray, start: np.ndarray | None,
                       sigma_px: float, iterations: int, step_tolerance: float
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(points (N, 3), residuals (N, C, 2) px, rms (N,) px, covariances (N, 3, 3) m^2)``.

    Cameras: ``K`` (C, 3, 3), ``dist`` (C, 5) plumb_bob, ``R`` (C, 3, 3) and ``t`` (C, 3) world into camera,
    ``projections`` (C, 3, 4) ``K [R | t]``. ``pixels``: (N, C, 2) observed, ``ideal``: the same undistorted,
    ``seen``: (N, C) bool; ``start``: (N, 3) starting points, or None for the DLT's. Gauss-Newton stops at a
    step that does not lower the error or is shorter than ``step_tolerance`` m (not taken), or after
    ``iterations``. A point at infinity stays NaN, with rms inf and covariance NaN. Shapes are not checked.
    """
    def c(a: np.ndarray) -> np.ndarray:
        return np.ascontiguousarray(a, np.float64)

    return _triangulate(c(K), c(dist), c(R), c(t), c(projections), c(pixels), c(ideal),
                        np.ascontiguousarray(seen, bool), _NO_START if start is None else c(start), start is not None,
                        float(sigma_px), int(iterations), float(step_tolerance))


_NO_START = np.zeros((0, 3))


@njit(cache=True, nogil=True)
def _triangulate(K: np.ndarray, dist: np.ndarray, R: np.ndarray, t: np.ndarray, projections: np.ndarray,
                 pixels: np.ndarray, ideal: np.ndarray, seen: np.ndarray, start: np.ndarray, has_start: bool,
                 sigma_px: float, iterations: int, step_tolerance: float
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``triangulate_points`` on contiguous arrays, ``start`` used when ``has_start``."""
    count, cameras = seen.shape
    points = np.full((count, 3), np.nan)
    residuals = np.zeros((count, cameras, 2))
    rms = np.full(count, np.inf)
    covariances = np.full((count, 3, 3), np.nan)
    J = np.empty((2 * cameras, 3))
    candidate_residuals = np.empty((cameras, 2))
    candidate_J = np.empty((2 * cameras, 3))
    for n in range(count):
        X = start[n].copy() if has_start else _dlt(projections, ideal[n], seen[n])
        error = _evaluate(K, dist, R, t, pixels[n], seen[n], X, residuals[n], J)
        finite = np.all(np.isfinite(X))
        if finite:
            for _ in range(iterations):
                A, b = _normal(J, residuals[n].ravel())
                step = -(_inverse(A) @ b)
                if np.sqrt(np.sum(step**2)) < step_tolerance:
                    break
                candidate = X + step
                new_error = _evaluate(K, dist, R, t, pixels[n], seen[n], candidate, candidate_residuals, candidate_J)
                if not new_error <= error:
                    break
                X, error = candidate, new_error
                residuals[n] = candidate_residuals
                J[:] = candidate_J
        points[n] = X
        information, _ = _normal(J, residuals[n].ravel())
        if finite and np.all(np.isfinite(information)):
            covariances[n] = _inverse(information) * sigma_px**2
            rms[n] = np.sqrt(error / max(np.sum(seen[n]), 1))
    return points, residuals, rms, covariances


def warm() -> None:
    """Compile ``triangulate_points`` (or load it from the disk cache) on one point seen by two cameras."""
    K = np.array([[[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]]] * 2)
    R = np.array([np.eye(3)] * 2)
    t = np.array([[0.0, 0.0, 0.0], [-0.1, 0.0, 0.0]])
    projections = np.ascontiguousarray(K @ np.concatenate([R, t[:, :, None]], axis=2))
    pixels = np.array([[[320.0, 240.0], [295.0, 240.0]]])
    triangulate_points(K, np.zeros((2, 5)), R, t, projections, pixels, pixels, np.ones((1, 2), bool), None, 1.0, 10,
                       1e-10)
