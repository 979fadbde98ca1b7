"""Plane-to-image homographies: the normalised DLT, and the pose of a plane from its homography.

Points are (N, 2) float64. ``H`` maps homogeneous source points to destination points:
``dst ~ H @ [x, y, 1]``. For a planar target, source points are target-plane coordinates in
metres (the target frame's z = 0 plane) and destination points are pixels.
"""

from __future__ import annotations

import numpy as np

from services.geometry.rotation import nearest_rotation
from services.geometry.shapes import check_shape


class DegenerateError(ValueError):
    """The points do not determine the quantity asked for (too few, collinear, coincident)."""


def normalising_transform(points: np.ndarray) -> np.ndarray:
    """(d+1, d+1) similarity moving (N, d) ``points`` to mean 0 and RMS distance sqrt(d) from it (Hartley)."""
    points = check_shape(points, "N,D", "points", np.float64)
    d = points.shape[1]
    centre = points.mean(axis=0)
    rms = np.sqrt(np.mean(np.sum((points - centre) ** 2, axis=1)))
    if rms < 1e-12:
        raise DegenerateError("all points coincide")
    s = np.sqrt(d) / rms
    T = np.diag([*([s] * d), 1.0])
    T[:d, d] = -s * centre
    return T


def homography_dlt(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """(3, 3) homography with ``H[2, 2] = 1`` from N >= 4 correspondences, by the normalised DLT.

    Both point sets are normalised (mean 0, RMS sqrt(2)), the 2N x 9 system is solved by SVD
    (right singular vector of the smallest singular value), and the result denormalised.
    Raises DegenerateError when the system has no unique solution (e.g. three collinear of four).
    """
    src = check_shape(src, "N,2", "src", np.float64)
    dst = check_shape(dst, f"{len(src)},2", "dst", np.float64)
    if len(src) < 4:
        raise DegenerateError(f"need N >= 4 matching points, got {len(src)}")
    T_src, T_dst = normalising_transform(src), normalising_transform(dst)
    a = src @ T_src[:2, :2].T + T_src[:2, 2]
    b = dst @ T_dst[:2, :2].T + T_dst[:2, 2]
    n = len(a)
    A = np.zeros((2 * n, 9))
    A[0::2, 0:2], A[0::2, 2] = a, 1.0
    A[0::2, 6:8], A[0::2, 8] = -b[:, :1] * a, -b[:, 0]
    A[1::2, 3:5], A[1::2, 5] = a, 1.0
    A[1::2, 6:8], A[1::2, 8] = -b[:, 1:] * a, -b[:, 1]
    _, singular, Vt = np.linalg.svd(A)
    if singular[7] < 1e-10 * singular[0]:
        raise DegenerateError("the correspondences do not determine a unique homography")
    H = np.linalg.inv(T_dst) @ Vt[-1].reshape(3, 3) @ T_src
    if abs(H[2, 2]) < 1e-15:
        raise DegenerateError("the homography maps the source origin to infinity")
    return H / H[2, 2]


def pose_from_homography(H: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(4, 4) ``T_camera_plane`` from a plane-to-pixel homography and the intrinsics ``K``.

    ``K^-1 H = lambda [r1 r2 t]``: lambda is the mean of the two column norms, ``r3 = r1 x r2``,
    R is projected onto the nearest rotation (SVD), and the sign is chosen so the plane lies
    in front of the camera (t_z > 0).
    """
    M = np.linalg.solve(check_shape(K, "3,3", "K", np.float64), check_shape(H, "3,3", "H", np.float64))
    scale = (np.linalg.norm(M[:, 0]) + np.linalg.norm(M[:, 1])) / 2
    if scale < 1e-12:
        raise DegenerateError("the homography has no rotation part")
    M = M / scale
    if M[2, 2] < 0:
        M = -M
    R = nearest_rotation(np.column_stack([M[:, 0], M[:, 1], np.cross(M[:, 0], M[:, 1])]))
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, M[:, 2]
    return T


def transfer_errors(H: np.ndarray, src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """(N, 2) transfer distances of N matches ``src[i]``, ``dst[i]`` (both (N, 2)) under ``dst ~ H src``:
    column 0 ``|src - H^-1 dst|``, column 1 ``|dst - H src|``; inf where a point maps to infinity."""
    H = check_shape(H, "3,3", "H", np.float64)
    src = check_shape(src, "N,2", "src", np.float64)
    dst = check_shape(dst, f"{len(src)},2", "dst", np.float64)
    columns = []
    for M, start, end in ((np.linalg.inv(H), dst, src), (H, src, dst)):
        mapped = np.hstack([start, np.ones((len(start), 1))]) @ M.T
        with np.errstate(divide="ignore", invalid="ignore"):
            distance = np.linalg.norm(mapped[:, :2] / mapped[:, 2:] - end, axis=1)
        columns.append(np.where(np.isfinite(distance), distance, np.inf))
    return np.column_stack(columns)
