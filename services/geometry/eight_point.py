"""The normalised eight-point algorithm: a fundamental matrix from N >= 8 correspondences, and the
essential matrix it implies for calibrated cameras.

Pixels are (N, 2) float64 ideal pinhole pixels (undistorted, see ``camera.undistort_pixels``);
``pixels_a[i]`` in camera a and ``pixels_b[i]`` in camera b see the same point, so that
``x_b^T F_b_a x_a = 0`` for their homogeneous forms (as ``cv2.findFundamentalMat(pixels_a, pixels_b)``).
No outlier rejection: a least-squares fit of every correspondence given.
"""

from __future__ import annotations

import numpy as np

from services.geometry.homography import DegenerateError, normalising_transform
from services.geometry.shapes import check_shape

__all__ = ["eight_point_fundamental", "essential_from_fundamental"]


def eight_point_fundamental(pixels_a: np.ndarray, pixels_b: np.ndarray) -> np.ndarray:
    """(3, 3) ``F_b_a`` of rank 2 and unit Frobenius norm from N >= 8 correspondences (Hartley).

    Each image's points are moved to mean 0 and RMS distance sqrt(2); each correspondence gives
    one row of ``A f = 0`` (``f``: F row by row); ``f`` is the right singular vector of the
    smallest singular value; the smallest singular value of F is then set to zero (the closest
    rank-2 matrix in the Frobenius norm) and the normalisation undone. DegenerateError when the
    points do not determine F (fewer than eight, or a two-dimensional null space).
    """
    a = check_shape(pixels_a, "N,2", "pixels_a", np.float64)
    b = check_shape(pixels_b, "N,2", "pixels_b", np.float64)
    if len(a) != len(b) or len(a) < 8:
        raise DegenerateError(f"need N >= 8 matching (N, 2) points, got {len(a)} and {len(b)}")
    T_a, T_b = normalising_transform(a), normalising_transform(b)
    xa = a @ T_a[:2, :2].T + T_a[:2, 2]
    xb = b @ T_b[:2, :2].T + T_b[:2, 2]
    ha = np.hstack([xa, np.ones((len(xa), 1))])
    hb = np.hstack([xb, np.ones((len(xb), 1))])
    A = (hb[:, :, None] * ha[:, None, :]).reshape(-1, 9)
    _, singular, Vt = np.linalg.svd(A)
    if len(singular) == 9 and singular[7] < 1e-10 * singular[0]:
        raise DegenerateError("the correspondences do not determine a unique fundamental matrix")
    U, s, Vt_f = np.linalg.svd(Vt[-1].reshape(3, 3))
    F = T_b.T @ (U @ np.diag([s[0], s[1], 0.0]) @ Vt_f) @ T_a
    return F / np.linalg.norm(F)


def essential_from_fundamental(F_b_a: np.ndarray, K_a: np.ndarray, K_b: np.ndarray) -> np.ndarray:
    """(3, 3) ``E_b_a = K_b^T F_b_a K_a`` projected onto the essential matrices: singular values (1, 1, 0).

    ``E_b_a`` relates normalised image points: ``y_b^T E_b_a y_a = 0`` with ``y = K^-1 x``; up to
    scale and sign it is ``[t]x R`` of ``T_b_a``.
    """
    E = (check_shape(K_b, "3,3", "K_b", np.float64).T @ check_shape(F_b_a, "3,3", "F_b_a", np.float64)
         @ check_shape(K_a, "3,3", "K_a", np.float64))
    U, _, Vt = np.linalg.svd(E)
    return U @ np.diag([1.0, 1.0, 0.0]) @ Vt
