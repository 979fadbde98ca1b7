"""Rigid transforms as (4, 4) homogeneous matrices.

``T_a_b`` maps coordinates in frame b to frame a: ``p_a = T_a_b @ p_b``; so
``T_a_c = T_a_b @ T_b_c`` and ``T_b_a = invert(T_a_b)``.
"""

from __future__ import annotations

import numpy as np

from services.geometry.rotation import matrix_from_quaternion, quaternion_from_matrix


def make_transform(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(4, 4) transform from a (3, 3) rotation and a (3,) translation."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t, dtype=np.float64).ravel()
    return T


def invert(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid (4, 4) transform, without a general matrix inverse."""
    R, t = T[:3, :3], T[:3, 3]
    return make_transform(R.T, -R.T @ t)


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply ``T_a_b`` to (N, 3) points in frame b; returns (N, 3) points in frame a."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    return points @ T[:3, :3].T + T[:3, 3]


def to_quaternion_translation(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(q, t)``: (4,) quaternion (x, y, z, w) and (3,) translation of a (4, 4) transform."""
    return quaternion_from_matrix(T[:3, :3]), T[:3, 3].copy()


def from_quaternion_translation(q: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(4, 4) transform from a quaternion (x, y, z, w) and a (3,) translation."""
    return make_transform(matrix_from_quaternion(q), t)
