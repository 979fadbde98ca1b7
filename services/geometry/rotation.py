"""Rotations: matrices, unit quaternions (x, y, z, w) and rotation vectors.

Matrices are (3, 3) float64 proper rotations. Quaternions follow the Hamilton convention
with the scalar last, ``q = (x, y, z, w)``, the order the protocol, scipy and Rerun use;
``q`` and ``-q`` are the same rotation, and functions here return ``w >= 0``.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from services.geometry.shapes import check_shape


def quaternion_from_matrix(R: np.ndarray) -> np.ndarray:
    """(4,) unit quaternion (x, y, z, w), w >= 0, of the (3, 3) rotation ``R`` (``quaternion_of_rows``)."""
    return np.array(quaternion_of_rows(check_shape(R, "3,3", "R", np.float64).tolist()))


def quaternion_of_rows(R: list[list[float]]) -> tuple[float, float, float, float]:
    """Unit quaternion (x, y, z, w), w >= 0, of a rotation given as rows of Python floats: at least three
    rows of at least three numbers, the (3, 3) block read (``T.tolist()`` of a (4, 4) transform will do).

    Shepperd's method: pick the largest of the four squared components to divide by,
    so the result stays accurate near 180 degrees. Worked on Python floats: nine numbers do
    not repay numpy's per-call cost, paid once per published pose (docs/benchmarks.md).
    """
    trace = R[0][0] + R[1][1] + R[2][2]
    squares = [1 + 2 * R[0][0] - trace, 1 + 2 * R[1][1] - trace, 1 + 2 * R[2][2] - trace, 1 + trace]
    i = max(range(4), key=squares.__getitem__)
    q = [0.0] * 4
    q[i] = math.sqrt(max(squares[i], 0.0)) / 2
    d = 4 * q[i]
    if i == 3:
        q[0], q[1], q[2] = (R[2][1] - R[1][2]) / d, (R[0][2] - R[2][0]) / d, (R[1][0] - R[0][1]) / d
    else:
        j, k = (i + 1) % 3, (i + 2) % 3
        q[j] = (R[j][i] + R[i][j]) / d
        q[k] = (R[k][i] + R[i][k]) / d
        q[3] = (R[k][j] - R[j][k]) / d
    sign = (1.0 if q[3] >= 0 else -1.0) / math.sqrt(sum(v * v for v in q))
    x, y, z, w = (v * sign for v in q)
    return x, y, z, w


def matrix_from_quaternion(q: np.ndarray) -> np.ndarray:
    """(3, 3) rotation of the quaternion ``q`` = (x, y, z, w) (normalised first)."""
    q = check_shape(q, "4", "q", np.float64)
    x, y, z, w = q / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def matrix_from_rotvec(rotvec: np.ndarray) -> np.ndarray:
    """(3, 3) rotation of a rotation vector (axis * angle, radians) of 3 values ((3,), or OpenCV's (3, 1)), via
    cv2.Rodrigues."""
    return cv2.Rodrigues(check_shape(np.ravel(rotvec), "3", "rotvec", np.float64).reshape(3, 1))[0]


def rotvec_from_matrix(R: np.ndarray) -> np.ndarray:
    """(3,) rotation vector (axis * angle, radians) of the (3, 3) rotation ``R``.

    Through the quaternion, which stays accurate for tiny angles where cv2.Rodrigues
    rounds to zero.
    """
    q = quaternion_from_matrix(R)
    sin_half = np.linalg.norm(q[:3])
    if sin_half < 1e-300:
        return np.zeros(3)
    return q[:3] / sin_half * 2 * np.arctan2(sin_half, q[3])


def rotation_angles(R: np.ndarray) -> np.ndarray:
    """(...,) angles (radians, in [0, pi]) of the (..., 3, 3) rotations ``R``.

    ``atan2(|vee(R - R^T)| / 2, (trace(R) - 1) / 2)``: the sine and the cosine of the angle together,
    accurate to a few 1e-16 rad across [0, pi]. The cosine alone (an arccos of the trace) resolves
    an angle ``d`` from 0 or from pi only to about 1e-8 rad: ``cos = +-(1 - d^2 / 2)`` rounds ``d``
    below that away.
    """
    R = check_shape(R, "*,3,3", "R", np.float64)
    cos = (np.trace(R, axis1=-2, axis2=-1) - 1) / 2
    vee = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], axis=-1)
    return np.arctan2(np.linalg.norm(vee, axis=-1) / 2, cos)


def rotation_angle(R_a: np.ndarray, R_b: np.ndarray) -> float:
    """Angle (radians, in [0, pi]) of the rotation taking ``R_b`` to ``R_a`` (see ``rotation_angles``)."""
    R_a, R_b = check_shape(R_a, "3,3", "R_a", np.float64), check_shape(R_b, "3,3", "R_b", np.float64)
    return float(rotation_angles(R_a.T @ R_b))


def nearest_rotation(M: np.ndarray) -> np.ndarray:
    """The proper rotation closest to the (3, 3) matrix ``M`` in the Frobenius norm (SVD)."""
    U, _, Vt = np.linalg.svd(check_shape(M, "3,3", "M", np.float64))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt
