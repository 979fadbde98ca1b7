"""Geometry of two views of one calibrated camera: robust essential matrix and homography, the
relative pose each implies, triangulation, parallax and cheirality.

Pixels are (N, 2) float64 ideal pinhole pixels (undistorted with ``camera.undistort_pixels``, same
``K``); ``pixels_a[i]`` in view a and ``pixels_b[i]`` in view b are one match. Camera frames are
OpenCV's (x right, y down, z forward). ``T_b_a`` (4, 4) maps view a's camera frame into view b's;
monocular scale is arbitrary, so its translation has unit norm. Points are (N, 3) float64 in view
a's camera frame.

The essential matrix comes from OpenCV's USAC (``cv2.USAC_ACCURATE``: uniform sampling, MSAC score,
graph-cut local optimisation), on the ``room`` scene's geometry the steadier of it and ``USAC_MAGSAC``.

OpenCV's USAC all the same settles, in some draws, on a model that explains the matches clearly
worse than the true pose does (a view facing a wall): a second hypothesis comes from pycolmap's LO-RANSAC of the
relative pose with a final Gauss-Newton refinement of the Sampson error over its inliers
(``fit_relative_pose``), and the caller takes it when it is clearly better supported
(``support_gain``). Even the best
supported pose is only as good as the matches determine it: ``pose_std_deg`` is its predicted
standard deviation from the Sampson error's Jacobian.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import pycolmap

from services.geometry.camera import CameraModel
from services.geometry.camera_stack import CameraStack
from services.geometry.epipolar import fundamental_matrix, matched_epipolar_distances, sampson_distances
from services.geometry.homography import transfer_errors
from services.geometry.rotation import matrix_from_rotvec
from services.geometry.se3 import invert, make_transform
from services.geometry.triangulation import triangulate_many

__all__ = ["ESSENTIAL_METHOD", "Triangulated", "fit_essential", "fit_homography", "fit_relative_pose",
           "essential_support", "homography_support", "support_gain", "pose_std_deg", "pose_from_essential",
           "rotations_from_essential", "poses_from_homography", "triangulate_pair", "ray_parallax_deg"]

ESSENTIAL_METHOD = cv2.USAC_ACCURATE
HOMOGRAPHY_METHOD = cv2.USAC_MAGSAC
MAX_ITERATIONS = 1000
MIN_DEPTH_M = 1e-9
"""A point is in front of a camera when its depth exceeds this (in units of the baseline)."""
CHI2_ONE_DOF, CHI2_TWO_DOF = 3.841, 5.991
"""95 % quantiles of the chi-square distribution: a point-to-line distance has one degree of freedom, a
point-to-point transfer error two."""


def fit_essential(pixels_a: np.ndarray, pixels_b: np.ndarray, K: np.ndarray, threshold_px: float,
                  confidence: float) -> tuple[np.ndarray | None, np.ndarray]:
    """``(E_b_a (3, 3) or None, inliers (N,) bool)`` by USAC (``ESSENTIAL_METHOD``); ``threshold_px``
    bounds a match's distance to its epipolar line. None (and no inliers) when nothing was found.

    USAC is given normalised coordinates (``K^-1`` applied, the threshold divided by the focal
    length): with pixels and KITTI's ``K`` (1226 x 370 px, principal point 10 px left of the centre)
    OpenCV 5.0's USAC essential estimators returned nothing on 384 good matches, which plain
    RANSAC fitted with 328 inliers; in normalised coordinates USAC found 362."""
    if len(pixels_a) < 5:
        return None, np.zeros(len(pixels_a), bool)
    K_inv = np.linalg.inv(K)
    normalised_a = pixels_a @ K_inv[:2, :2].T + K_inv[:2, 2]
    normalised_b = pixels_b @ K_inv[:2, :2].T + K_inv[:2, 2]
    E, mask = cv2.findEssentialMat(normalised_a, normalised_b, np.eye(3), method=ESSENTIAL_METHOD, prob=confidence,
                                   threshold=threshold_px / float(np.sqrt(K[0, 0] * K[1, 1])),
                                   maxIters=MAX_ITERATIONS)
    if E is None or E.shape[0] < 3 or mask is None:
        return None, np.zeros(len(pixels_a), bool)
    return E[:3], mask.ravel().astype(bool)


def fit_homography(pixels_a: np.ndarray, pixels_b: np.ndarray, threshold_px: float,
                   confidence: float) -> tuple[np.ndarray | None, np.ndarray]:
    """``(H_b_a (3, 3) or None, inliers (N,) bool)`` with ``x_b ~ H_b_a x_a``, by USAC MAGSAC++;
    ``threshold_px`` bounds the transfer error in view b."""
    if len(pixels_a) < 4:
        return None, np.zeros(len(pixels_a), bool)
    H, mask = cv2.findHomography(pixels_a, pixels_b, HOMOGRAPHY_METHOD, threshold_px, maxIters=MAX_ITERATIONS,
                                 confidence=confidence)
    if H is None or mask is None:
        return None, np.zeros(len(pixels_a), bool)
    return H, mask.ravel().astype(bool)


def fit_relative_pose(pixels_a: np.ndarray, pixels_b: np.ndarray, K: np.ndarray, threshold_px: float,
                      confidence: float) -> tuple[np.ndarray | None, np.ndarray]:
    """``(T_b_a (4, 4) with unit translation, or None; inliers (N,) bool)`` by pycolmap's LO-RANSAC of the
    relative pose (five-point samples, ``threshold_px`` on the Sampson error, at most ``MAX_ITERATIONS``
    samples, a fixed random seed) refined over its inliers by ``pycolmap.refine_relative_pose``."""
    if len(pixels_a) < 5:
        return None, np.zeros(len(pixels_a), bool)
    camera = pycolmap.Camera(model="PINHOLE", width=int(2 * K[0, 2]) + 1, height=int(2 * K[1, 2]) + 1,
                             params=[K[0, 0], K[1, 1], K[0, 2], K[1, 2]])
    options = pycolmap.RANSACOptions()
    options.max_error, options.confidence, options.random_seed = threshold_px, confidence, 0
    options.min_num_trials, options.max_num_trials = 100, MAX_ITERATIONS
    found = pycolmap.estimate_relative_pose(camera, pixels_a, camera, pixels_b, options)
    if found is None:
        return None, np.zeros(len(pixels_a), bool)
    inliers = np.asarray(found["inlier_mask"], bool).ravel()
    refined = pycolmap.refine_relative_pose(found["cam2_from_cam1"], camera, pixels_a, camera, pixels_b, inliers)
    matrix = (refined or found)["cam2_from_cam1"].matrix()
    norm = np.linalg.norm(matrix[:, 3])
    if not norm > 0:
        return None, np.zeros(len(pixels_a), bool)
    return make_transform(matrix[:, :3], matrix[:, 3] / norm), inliers


def support_gain(T_base: np.ndarray, T_other: np.ndarray, K: np.ndarray, pixels_a: np.ndarray,
                 pixels_b: np.ndarray, sigma_px: float) -> float:
    """How much better the (4, 4) pose ``T_other`` explains the matches than ``T_base``, in standard
    deviations: the difference of their ``essential_support`` over the root sum of squares of the
    per-match differences (a paired test on the same matches; 0 when both explain them alike)."""
    def contributions(T: np.ndarray) -> np.ndarray:
        errors = matched_epipolar_distances(fundamental_matrix(K, K, T), pixels_a, pixels_b)
        return _contributions(errors, sigma_px, CHI2_ONE_DOF)

    differences = contributions(T_other) - contributions(T_base)
    spread = float(np.sqrt(np.sum(differences**2)))
    return float(differences.sum()) / spread if spread > 0 else 0.0


def pose_std_deg(T_b_a: np.ndarray, K: np.ndarray, pixels_a: np.ndarray, pixels_b: np.ndarray,
                 sigma_px: float) -> tuple[float, float]:
    """Predicted standard deviation, degrees, of the rotation and of the translation direction of
    ``T_b_a`` (4, 4) fitted to the inlier matches (N, 2) + (N, 2) with isotropic pixel noise ``sigma_px``:
    ``sigma^2 (J^T J)^-1`` with ``J`` (N, 5) the Jacobian of the Sampson distances
    (``epipolar.sampson_distances``, of variance ``sigma^2``) in a left rotation increment (3) and
    the two directions orthogonal to the translation (2), by central differences; the two figures
    are the square roots of the traces of the two blocks. Infinite when the Jacobian is singular."""
    R, t = T_b_a[:3, :3], T_b_a[:3, 3] / np.linalg.norm(T_b_a[:3, 3])
    tangent = np.linalg.svd(t[None])[2][1:]

    def distances(step: np.ndarray) -> np.ndarray:
        direction = t + tangent.T @ step[3:]
        T = make_transform(matrix_from_rotvec(step[:3]) @ R, direction / np.linalg.norm(direction))
        return sampson_distances(fundamental_matrix(K, K, T), pixels_a, pixels_b)

    h = 1e-6
    J = np.column_stack([(distances(h * e) - distances(-h * e)) / (2 * h) for e in np.eye(5)])
    try:
        covariance = sigma_px**2 * np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        return float("inf"), float("inf")
    return (float(np.degrees(np.sqrt(max(np.trace(covariance[:3, :3]), 0.0)))),
            float(np.degrees(np.sqrt(max(np.trace(covariance[3:, 3:]), 0.0)))))


def essential_support(E_b_a: np.ndarray, K: np.ndarray, pixels_a: np.ndarray, pixels_b: np.ndarray,
                      sigma_px: float) -> float:
    """How well ``E_b_a`` explains the matches, on the same scale as ``homography_support``: over the
    matches whose epipolar distance in both images is within the one-degree-of-freedom 95 % bound
    (``(d / sigma_px)^2 <= CHI2_ONE_DOF``), the sum of ``CHI2_TWO_DOF - (d / sigma_px)^2``."""
    K_inv = np.linalg.inv(K)
    return _support(matched_epipolar_distances(K_inv.T @ E_b_a @ K_inv, pixels_a, pixels_b), sigma_px, CHI2_ONE_DOF)


def homography_support(H_b_a: np.ndarray, pixels_a: np.ndarray, pixels_b: np.ndarray, sigma_px: float) -> float:
    """``essential_support`` for a homography: transfer errors both ways, bounded by ``CHI2_TWO_DOF``."""
    return _support(transfer_errors(H_b_a, pixels_a, pixels_b), sigma_px, CHI2_TWO_DOF)


def _support(errors_px: np.ndarray, sigma_px: float, bound: float) -> float:
    """Sum of ``CHI2_TWO_DOF - chi2`` over both images of the (N, 2) errors' matches within ``bound``.

    Both models are scored against the same ``CHI2_TWO_DOF`` so that a match explained equally well
    counts the same whichever model explains it (ORB-SLAM's scoring)."""
    return float(np.sum(_contributions(errors_px, sigma_px, bound)))


def _contributions(errors_px: np.ndarray, sigma_px: float, bound: float) -> np.ndarray:
    """(N,) each match's term of ``_support``: ``CHI2_TWO_DOF - chi2`` summed over both images when
    both are within ``bound``, else 0."""
    chi2 = (errors_px / sigma_px) ** 2
    return np.where(np.all(chi2 <= bound, axis=1), np.sum(CHI2_TWO_DOF - chi2, axis=1), 0.0)


def pose_from_essential(E: np.ndarray, pixels_a: np.ndarray, pixels_b: np.ndarray, K: np.ndarray,
                        inliers: np.ndarray) -> np.ndarray:
    """(4, 4) ``T_b_a``, translation of unit norm: the decomposition of ``E`` that puts the most
    ``inliers`` ((N,) bool) in front of both cameras (``cv2.recoverPose``'s cheirality check)."""
    mask = inliers.astype(np.uint8).reshape(-1, 1)
    _, R, t, _ = cv2.recoverPose(E, pixels_a, pixels_b, K, mask=mask)
    return make_transform(R, t.ravel() / np.linalg.norm(t))


def rotations_from_essential(E: np.ndarray) -> list[np.ndarray]:
    """The two (3, 3) rotations ``R_b_a`` of the decomposition of ``E`` (``cv2.decomposeEssentialMat``);
    with ``t`` or ``-t`` each makes one of the four poses, which the cheirality check tells apart."""
    R1, R2, _ = cv2.decomposeEssentialMat(E)
    return [R1, R2]


def poses_from_homography(H: np.ndarray, K: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """Every ``(T_b_a (4, 4), n_a (3,))`` of ``cv2.decomposeHomographyMat`` (up to four; translations scaled
    to unit norm, left as they are when zero; ``n_a`` the plane's unit normal in view a's frame): which one
    is right is for the caller's cheirality check."""
    _, rotations, translations, normals = cv2.decomposeHomographyMat(H, K)
    poses = []
    for R, t, n in zip(rotations, translations, normals, strict=True):
        t, n = t.ravel(), n.ravel()
        t_norm, n_norm = np.linalg.norm(t), np.linalg.norm(n)
        poses.append((make_transform(R, t / t_norm if t_norm > 0 else t), n / n_norm if n_norm > 0 else n))
    return poses


@dataclass(frozen=True)
class Triangulated:
    """Matches triangulated from two views: ``points`` (N, 3) view a's frame (NaN where the rays are
    parallel), ``rms_px`` (N,) reprojection error over both views (inf where it failed),
    ``in_front`` (N,) bool, positive depth in both views."""

    points: np.ndarray
    rms_px: np.ndarray
    in_front: np.ndarray


def triangulate_pair(K: np.ndarray, T_b_a: np.ndarray, pixels_a: np.ndarray, pixels_b: np.ndarray) -> Triangulated:
    """The (N, 2) + (N, 2) matches triangulated (linear DLT refined by Gauss-Newton on the reprojection
    error, ``geometry.triangulation.triangulate_many``) with view a at the origin and view b at ``T_b_a``."""
    cameras = [CameraModel(name, 0, 0, K, np.zeros(5), T) for name, T in (("a", np.eye(4)), ("b", invert(T_b_a)))]
    stack = CameraStack.of(cameras)
    pixels = np.stack([pixels_a, pixels_b], axis=1)
    found = triangulate_many(stack, pixels, np.ones(pixels.shape[:2], bool), 1.0, ideal=pixels)
    with np.errstate(invalid="ignore"):
        in_front = np.all(stack.depths(found.points) > MIN_DEPTH_M, axis=1)
    return Triangulated(found.points, found.rms_px, in_front)


def ray_parallax_deg(R_b_a: np.ndarray, K: np.ndarray, pixels_a: np.ndarray, pixels_b: np.ndarray) -> np.ndarray:
    """(N,) angle, degrees, between each match's two rays: ``K^-1 x_a`` of view a and ``R_b_a^T K^-1 x_b``
    of view b turned into view a's frame, ``R_b_a`` (3, 3) the rotation of ``T_b_a``. For a point in front
    of both cameras it is the angle at the triangulated point between its directions to the two camera
    centres (its parallax), with no triangulation: on exact matches the two agree to numerical
    precision; a match triangulating behind one camera gives the supplement. A rotation only: the rays
    of a match coincide (0)."""
    K_inv = np.linalg.inv(K)
    rays_a = np.column_stack([pixels_a, np.ones(len(pixels_a))]) @ K_inv.T
    rays_b = np.column_stack([pixels_b, np.ones(len(pixels_b))]) @ K_inv.T @ R_b_a
    cos = np.sum(rays_a * rays_b, axis=1) / (np.linalg.norm(rays_a, axis=1) * np.linalg.norm(rays_b, axis=1))
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
