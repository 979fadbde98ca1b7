"""Linear camera calibration: the projection matrix from 3D-2D correspondences, and its factors.

``P`` (3, 4) maps homogeneous world points to homogeneous pixels, ``[u, v, 1] ~ P @ [X, Y, Z, 1]``,
and factors as ``P ~ K [R | t]`` with ``K`` (3, 3) upper triangular (the intrinsics) and
``[R | t]`` = ``T_camera_world`` (camera frame as OpenCV's: x right, y down, z forward).
Distortion is not modelled: use undistorted pixels, or read the result as a starting point.
"""

from __future__ import annotations

import numpy as np

from services.geometry.homography import DegenerateError, normalising_transform

MIN_POINTS = 6
SINGULAR_GAP = 2.0
"""The second smallest singular value of the normalised system must exceed the smallest by this
factor: closer, and two different cameras explain the data about as well (coplanar points or
noise that swamps the geometry)."""


def projection_dlt(points_3d: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """(3, 4) projection matrix from N >= 6 correspondences of (N, 3) world points and (N, 2) pixels.

    Normalised DLT: world points to mean 0 and RMS sqrt(3), pixels to mean 0 and RMS sqrt(2);
    the 2N x 12 system is solved by SVD and the result denormalised. ``P`` is scaled so its
    third row's first three entries have unit norm and ``det(P[:, :3]) > 0``: then
    ``P[2] @ [X, 1]`` is the depth of X along the optical axis, positive in front of the camera.
    Raises DegenerateError for fewer than 6 points, coplanar or collinear points, or data
    that leaves the solution undetermined (see ``SINGULAR_GAP``).
    """
    points_3d, pixels = np.asarray(points_3d, dtype=np.float64), np.asarray(pixels, dtype=np.float64)
    if points_3d.ndim != 2 or points_3d.shape[1] != 3 or pixels.shape != (len(points_3d), 2):
        raise DegenerateError(f"need matching (N, 3) and (N, 2) points, got {points_3d.shape} and {pixels.shape}")
    if len(points_3d) < MIN_POINTS:
        raise DegenerateError(f"need at least {MIN_POINTS} correspondences for a projection matrix, "
                              f"got {len(points_3d)}")
    T_3d, T_2d = normalising_transform(points_3d), normalising_transform(pixels)
    X = np.column_stack([points_3d, np.ones(len(points_3d))]) @ T_3d.T
    x = pixels @ T_2d[:2, :2].T + T_2d[:2, 2]
    A = np.zeros((2 * len(X), 12))
    A[0::2, 0:4], A[0::2, 8:12] = X, -x[:, :1] * X
    A[1::2, 4:8], A[1::2, 8:12] = X, -x[:, 1:] * X
    _, singular, Vt = np.linalg.svd(A)
    if singular[10] < 1e-10 * singular[0]:
        raise DegenerateError("the points do not determine a projection matrix "
                              "(coplanar or collinear world points)")
    if singular[10] < SINGULAR_GAP * singular[11]:
        raise DegenerateError(f"the projection matrix is ill-determined: the two smallest singular values "
                              f"{singular[10]:.3g} and {singular[11]:.3g} are within a factor {SINGULAR_GAP} "
                              "(nearly coplanar points or too much noise)")
    P = np.linalg.inv(T_2d) @ Vt[-1].reshape(3, 4) @ T_3d
    P /= np.linalg.norm(P[2, :3])
    return -P if np.linalg.det(P[:, :3]) < 0 else P


def rq(M: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(U, Q)`` with ``M = U @ Q`` for a (3, 3) ``M``: U upper triangular, Q orthogonal.

    From numpy's QR of the row-reversed, transposed matrix: with ``E`` the exchange matrix,
    ``(E M)^T = Q' R'`` gives ``M = (E R'^T E)(E Q'^T)``.
    """
    E = np.eye(3)[::-1]
    Q_, R_ = np.linalg.qr((E @ M).T)
    return E @ R_.T @ E, E @ Q_.T


def decompose_projection(P: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(K, R, t)`` of a (3, 4) projection matrix: ``P ~ K [R | t]``.

    ``K`` (3, 3) upper triangular with a positive diagonal and ``K[2, 2] = 1``; ``R`` (3, 3) with
    ``det R = +1``; ``t`` (3,); ``[R | t]`` is ``T_camera_world``. The overall sign of ``P``
    is chosen so that ``det(P[:, :3]) > 0`` (otherwise no such K and R exist).
    Raises DegenerateError when ``P[:, :3]`` is singular.
    """
    P = np.asarray(P, dtype=np.float64)
    M = P[:, :3]
    det = np.linalg.det(M)
    if abs(det) <= 1e-12 * np.linalg.norm(M) ** 3:
        raise DegenerateError("P[:, :3] is singular: not the projection matrix of a finite camera")
    if det < 0:
        P, M = -P, -M
    U, Q = rq(M)
    signs = np.diag(np.sign(np.diag(U)))
    U, R = U @ signs, signs @ Q
    t = np.linalg.solve(U, P[:, 3])
    return U / U[2, 2], R, t
