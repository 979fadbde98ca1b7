"""Rigid transforms as (4, 4) homogeneous matrices.

``T_a_b`` maps coordinates in frame b to frame a: ``p_a = T_a_b @ p_b``; so
``T_a_c = T_a_b @ T_b_c`` and ``T_b_a = invert(T_a_b)``.
"""

from __future__ import annotations

import math

import numpy as np

from services.geometry.rotation import matrix_from_quaternion, quaternion_from_matrix
from services.geometry.shapes import check_shape


def make_transform(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(4, 4) transform from a (3, 3) rotation and a translation of 3 values ((3,), or OpenCV's (3, 1))."""
    T = np.eye(4)
    T[:3, :3] = check_shape(R, "3,3", "R")
    T[:3, 3] = check_shape(np.ravel(t), "3", "t", np.float64)
    return T


def invert(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid (4, 4) transform, without a general matrix inverse."""
    T = check_shape(T, "4,4", "T")
    R, t = T[:3, :3], T[:3, 3]
    return make_transform(R.T, -R.T @ t)


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply ``T_a_b`` (4, 4) to (N, 3) points in frame b (or one (3,) point); returns (N, 3) points in frame a."""
    T = check_shape(T, "4,4", "T")
    points = check_shape(points, "*,3", "points", np.float64).reshape(-1, 3)
    return points @ T[:3, :3].T + T[:3, 3]


def to_quaternion_translation(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(q, t)``: (4,) quaternion (x, y, z, w) and (3,) translation of a (4, 4) transform."""
    T = check_shape(T, "4,4", "T")
    return quaternion_from_matrix(T[:3, :3]), T[:3, 3].copy()


def from_quaternion_translation(q: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(4, 4) transform from a (4,) quaternion (x, y, z, w) and a (3,) translation."""
    return make_transform(matrix_from_quaternion(q), t)


def check_transform(T: np.ndarray, name: str = "T", tolerance: float = 1e-6) -> np.ndarray:
    """``T`` as a (4, 4) float64 array if it is a proper rigid transform, else ValueError naming ``name``.

    Proper rigid: finite, ``R^T R = I`` and ``det R = +1`` for the rotation block ``R = T[:3, :3]``
    (each within ``tolerance``), and last row ``(0, 0, 0, 1)``. A reflection (det -1), a scaled
    or sheared block, or a projective last row is refused. Worked on the 16 numbers as Python floats: a
    check made on every fitted pose costs a few microseconds so, against some 30 in numpy calls.
    """
    T = check_shape(T, "4,4", name, np.float64)
    rows = T.tolist()
    if not all(map(math.isfinite, rows[0] + rows[1] + rows[2] + rows[3])):
        raise ValueError(f"{name} must be finite, got NaN or infinity")
    last = rows[3]
    if max(abs(last[0]), abs(last[1]), abs(last[2]), abs(last[3] - 1.0)) > tolerance:
        raise ValueError(f"{name} must have last row (0, 0, 0, 1), got {tuple(last)}")
    (a, b, c, _), (d, e, f, _), (g, h, i, _) = rows[0], rows[1], rows[2]
    off = max(abs(a * a + d * d + g * g - 1.0), abs(b * b + e * e + h * h - 1.0), abs(c * c + f * f + i * i - 1.0),
              abs(a * b + d * e + g * h), abs(a * c + d * f + g * i), abs(b * c + e * f + h * i))
    if off > tolerance:
        raise ValueError(f"{name}[:3, :3] must be orthonormal (R^T R = I), off by {off:.3g}")
    det = a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g)
    if abs(det - 1.0) > tolerance:
        raise ValueError(f"{name}[:3, :3] must be a proper rotation (det +1), got det {det:.6g}")
    return T
