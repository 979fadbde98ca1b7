"""Epipolar geometry of two calibrated cameras: the fundamental matrix and point-to-line distances.

Pixels here are ideal pinhole pixels (undistorted, see ``camera.undistort_pixels``). For a
point seen at ``x_a`` in camera a and ``x_b`` in camera b (homogeneous (3,) pixels),
``x_b^T F_b_a x_a = 0``; ``F_b_a @ x_a`` is the epipolar line of ``x_a`` in image b.
"""

from __future__ import annotations

import numpy as np

from services.geometry.shapes import check_shape

__all__ = ["skew", "fundamental_matrix", "epipolar_distances", "matched_epipolar_distances", "sampson_distances",
           "near_lines"]

LINE_ROWS = 64
"""Epipolar lines per block of ``near_lines``."""


def skew(v: np.ndarray) -> np.ndarray:
    """(3, 3) matrix ``[v]x`` with ``[v]x @ w = cross(v, w)`` for a (3,) vector ``v``."""
    x, y, z = check_shape(v, "3", "v", np.float64)
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def fundamental_matrix(K_a: np.ndarray, K_b: np.ndarray, T_b_a: np.ndarray) -> np.ndarray:
    """(3, 3) ``F_b_a = K_b^-T [t]x R K_a^-1`` from the (3, 3) intrinsics and the (4, 4) ``T_b_a``
    (camera a's frame into camera b's), scaled to unit Frobenius norm."""
    K_a, K_b = check_shape(K_a, "3,3", "K_a"), check_shape(K_b, "3,3", "K_b")
    T_b_a = check_shape(T_b_a, "4,4", "T_b_a")
    E = skew(T_b_a[:3, 3]) @ T_b_a[:3, :3]
    F = np.linalg.inv(K_b).T @ E @ np.linalg.inv(K_a)
    return F / np.linalg.norm(F)


def epipolar_distances(F_b_a: np.ndarray, pixels_a: np.ndarray, pixels_b: np.ndarray) -> np.ndarray:
    """(Na, Nb) symmetric epipolar distance, px: for each pair, the larger of the distance from
    ``pixels_b[j]`` to the line of ``pixels_a[i]`` in image b and the reverse distance in image a.

    ``pixels_a``: (Na, 2), ``pixels_b``: (Nb, 2) ideal pinhole pixels; ``F_b_a`` (3, 3).
    """
    F_b_a = check_shape(F_b_a, "3,3", "F_b_a")
    xa = np.hstack([check_shape(pixels_a, "N,2", "pixels_a", np.float64), np.ones((len(pixels_a), 1))])
    xb = np.hstack([check_shape(pixels_b, "N,2", "pixels_b", np.float64), np.ones((len(pixels_b), 1))])
    lines_b = xa @ F_b_a.T
    lines_a = xb @ F_b_a
    algebraic = np.abs(xa @ F_b_a.T @ xb.T)
    in_b = algebraic / np.maximum(np.linalg.norm(lines_b[:, :2], axis=1), 1e-300)[:, None]
    in_a = algebraic / np.maximum(np.linalg.norm(lines_a[:, :2], axis=1), 1e-300)[None, :]
    return np.maximum(in_a, in_b)


def matched_epipolar_distances(F_b_a: np.ndarray, pixels_a: np.ndarray, pixels_b: np.ndarray) -> np.ndarray:
    """(N, 2) distances, px, of each match ``pixels_a[i]``, ``pixels_b[i]`` (both (N, 2) ideal pinhole
    pixels): column 0 from ``pixels_a[i]`` to the epipolar line of ``pixels_b[i]`` in image a, column 1
    from ``pixels_b[i]`` to the line of ``pixels_a[i]`` in image b."""
    F_b_a, xa, xb = _matched(F_b_a, pixels_a, pixels_b)
    lines_b = xa @ F_b_a.T
    lines_a = xb @ F_b_a
    algebraic = np.abs(np.sum(xb * lines_b, axis=1))
    return np.column_stack([algebraic / np.maximum(np.linalg.norm(lines_a[:, :2], axis=1), 1e-300),
                            algebraic / np.maximum(np.linalg.norm(lines_b[:, :2], axis=1), 1e-300)])


def sampson_distances(F_b_a: np.ndarray, pixels_a: np.ndarray, pixels_b: np.ndarray) -> np.ndarray:
    """(N,) signed Sampson distance, px, of each match ``pixels_a[i]``, ``pixels_b[i]`` (both (N, 2) ideal
    pinhole pixels): the first-order distance of the (4,) joint point to the variety ``x_b^T F x_a = 0``,
    ``x_b^T F x_a / |(l_b[:2], l_a[:2])|``; with isotropic noise of sigma px on every pixel its variance
    is sigma^2 (OpenCV's ``cv2.sampsonDistance`` returns its square for one match)."""
    F_b_a, xa, xb = _matched(F_b_a, pixels_a, pixels_b)
    lines_b = xa @ F_b_a.T
    lines_a = xb @ F_b_a
    norm = np.sqrt(np.sum(lines_b[:, :2] ** 2, axis=1) + np.sum(lines_a[:, :2] ** 2, axis=1))
    return np.sum(xb * lines_b, axis=1) / np.maximum(norm, 1e-300)


def _matched(F_b_a: np.ndarray, pixels_a: np.ndarray,
             pixels_b: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``F_b_a`` (3, 3) and the (N, 3) homogeneous ``pixels_a`` and ``pixels_b`` of N matches, once their shapes
    are checked."""
    F_b_a = check_shape(F_b_a, "3,3", "F_b_a")
    a = check_shape(pixels_a, "N,2", "pixels_a", np.float64)
    b = check_shape(pixels_b, f"{len(a)},2", "pixels_b", np.float64)
    return F_b_a, np.hstack([a, np.ones((len(a), 1))]), np.hstack([b, np.ones((len(b), 1))])


def near_lines(F_b_a: np.ndarray, pixels_a: np.ndarray, pixels_b: np.ndarray,
               bounds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(rows, columns)`` (P,) int64, in row-major order: the pairs of (Na, 2) ``pixels_a[rows]`` and
    (Nb, 2) ``pixels_b[columns]`` where the pixel of image b lies within its ``bounds`` (Nb,) px of the
    epipolar line of the pixel of image a (one-sided distances in float32, cheaper than
    ``epipolar_distances``; computed ``LINE_ROWS`` lines at a time, so that the distances stay in
    cache and are never all in memory at once)."""
    F_b_a = check_shape(F_b_a, "3,3", "F_b_a")
    pixels_a = check_shape(pixels_a, "N,2", "pixels_a")
    pixels_b = check_shape(pixels_b, "N,2", "pixels_b")
    bounds = check_shape(bounds, f"{len(pixels_b)}", "bounds", np.float32)
    lines = (np.hstack([pixels_a, np.ones((len(pixels_a), 1))]) @ F_b_a.T).astype(np.float32)
    lines /= np.maximum(np.linalg.norm(lines[:, :2], axis=1), 1e-30)[:, None]
    points = np.vstack([np.asarray(pixels_b, np.float64).T, np.ones(len(pixels_b))]).astype(np.float32)
    near = np.zeros((len(lines), len(pixels_b)), bool)
    distances = np.empty((min(LINE_ROWS, len(lines)), len(pixels_b)), np.float32)
    for start in range(0, len(lines), LINE_ROWS):
        chunk = lines[start:start + LINE_ROWS]
        out = distances[:len(chunk)]
        np.matmul(chunk, points, out=out)
        np.abs(out, out=out)
        np.less(out, bounds, out=near[start:start + len(chunk)])
    rows, columns = np.divmod(np.flatnonzero(near), max(len(pixels_b), 1))
    return rows, columns
