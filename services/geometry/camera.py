"""Pinhole camera: projection, plane homographies, look-at poses, rays and near-plane clipping.

Camera frame as OpenCV's: x right, y down, z forward. Pixel coordinates put the centre of
the top-left pixel at (0, 0). ``K`` is the (3, 3) intrinsic matrix; ``dist`` the OpenCV
plumb_bob coefficients (k1, k2, p1, p2, k3).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

from services.geometry.shapes import check_shape

UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)


@dataclass(frozen=True)
class CameraModel:
    """One calibrated camera.

    ``K``: (3, 3) float64; ``dist``: (5,) float64 OpenCV plumb_bob (k1, k2, p1, p2, k3);
    ``T_rig_camera``: (4, 4) float64, the camera's pose in its rig (or world) frame.
    """

    name: str
    width: int
    height: int
    K: np.ndarray
    dist: np.ndarray
    T_rig_camera: np.ndarray


def intrinsics(width: int, height: int, hfov_deg: float) -> np.ndarray:
    """(3, 3) K with square pixels, the principal point at the image centre and ``hfov_deg`` across."""
    f = width / (2.0 * np.tan(np.radians(hfov_deg) / 2.0))
    return np.array([[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0.0, 0.0, 1.0]])


def project_points(points_cam: np.ndarray, K: np.ndarray, dist: np.ndarray | None = None) -> np.ndarray:
    """(N, 2) float64 pixels of (N, 3) points in the camera frame (or one (3,) point) by the (3, 3) ``K``
    (cv2.projectPoints, with distortion).

    Points must lie in front of the camera (z > 0); behind it the result is meaningless.
    """
    points_cam = check_shape(points_cam, "*,3", "points_cam", np.float64).reshape(-1, 3)
    K = check_shape(K, "3,3", "K")
    if len(points_cam) == 0:
        return np.zeros((0, 2))
    dist = np.zeros(5) if dist is None else np.asarray(dist, dtype=np.float64)
    pixels, _ = cv2.projectPoints(points_cam, np.zeros(3), np.zeros(3), K, dist)
    return pixels.reshape(-1, 2)


def plane_homography(K: np.ndarray, T_cam_plane: np.ndarray) -> np.ndarray:
    """(3, 3) homography taking plane points (x, y, 1) (metres, z = 0 in the plane frame) to pixels.

    ``H = K [r1 r2 t]`` with ``T_cam_plane = [r1 r2 r3 t]`` ((3, 3) and (4, 4)); undistorted pinhole only.
    """
    return check_shape(K, "3,3", "K") @ check_shape(T_cam_plane, "4,4", "T_cam_plane")[:3, [0, 1, 3]]


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """(4, 4) ``T_world_camera`` of a camera at ``eye`` looking at ``target`` (both (3,), world frame).

    The camera's z axis points at the target and its y axis (image down) is as close to
    ``-up`` as the viewing direction allows. ``up`` must not be parallel to the view.
    """
    eye, target, up = (check_shape(a, "3", name, np.float64) for a, name in ((eye, "eye"), (target, "target"),
                                                                           (up, "up")))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    norm = np.linalg.norm(x)
    if norm < 1e-9:
        raise ValueError("look_at: the up vector is parallel to the viewing direction")
    x /= norm
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, np.cross(z, x), z, eye
    return T


def pixel_rays(K: np.ndarray, dist: np.ndarray, width: int, height: int) -> np.ndarray:
    """(height, width, 3) float32 unit rays, camera frame, of every pixel centre of the (3, 3) ``K``, through the
    distortion."""
    K = check_shape(K, "3,3", "K")
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    pixels = np.stack([u.ravel(), v.ravel()], axis=1)
    normalised = cv2.undistortPoints(pixels, K, np.asarray(dist, dtype=np.float64),
                                     criteria=UNDISTORT_CRITERIA).reshape(-1, 2)
    rays = np.concatenate([normalised, np.ones((len(normalised), 1))], axis=1)
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    return rays.reshape(height, width, 3).astype(np.float32)


def clip_polygon_near(polygon_cam: np.ndarray, z_near: float) -> np.ndarray:
    """Part of a convex (N, 3) polygon (camera frame, vertices in order) with z >= ``z_near``.

    Sutherland-Hodgman against the plane z = z_near; returns (M, 3), M = 0 when nothing is left.
    """
    polygon_cam = check_shape(polygon_cam, "N,3", "polygon_cam", np.float64)
    kept = []
    for i, current in enumerate(polygon_cam):
        previous = polygon_cam[i - 1]
        current_in, previous_in = current[2] >= z_near, previous[2] >= z_near
        if current_in != previous_in:
            s = (z_near - previous[2]) / (current[2] - previous[2])
            kept.append(previous + s * (current - previous))
        if current_in:
            kept.append(current)
    return np.array(kept).reshape(-1, 3)


def undistort_pixels(pixels: np.ndarray, K: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """(N, 2) ideal pinhole pixels (same (3, 3) ``K``, no distortion) of (N, 2) observed pixels (or one (2,) pixel)
    (cv2.undistortPoints)."""
    pixels = check_shape(pixels, "*,2", "pixels", np.float64).reshape(-1, 2)
    K = check_shape(K, "3,3", "K")
    if len(pixels) == 0:
        return np.zeros((0, 2))
    return cv2.undistortPoints(pixels.reshape(-1, 1, 2), K, np.asarray(dist, dtype=np.float64), P=K,
                               criteria=UNDISTORT_CRITERIA).reshape(-1, 2)


def undistort_image(image: np.ndarray, K: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """``image`` (H, W[, C]) taken by ``K`` (3, 3) with OpenCV distortion ``dist``, resampled (bilinear) as
    the distortion-free pinhole ``K`` sees it: what ``cv2.undistort`` gives, but the remap tables are
    made once per camera and image size rather than on every call."""
    h, w = image.shape[:2]
    K_key = tuple(check_shape(K, "3,3", "K", np.float64).ravel().tolist())
    dist_key = tuple(np.asarray(dist, dtype=np.float64).ravel().tolist())
    map_xy, map_fraction = _undistort_maps(K_key, dist_key, w, h)
    return cv2.remap(image, map_xy, map_fraction, cv2.INTER_LINEAR)


@lru_cache(maxsize=8)
def _undistort_maps(K: tuple[float, ...], dist: tuple[float, ...], width: int,
                    height: int) -> tuple[np.ndarray, np.ndarray]:
    """Fixed-point remap tables (``CV_16SC2`` and its fractions) of ``undistort_image``'s camera."""
    matrix = np.array(K).reshape(3, 3)
    map_xy, map_fraction = cv2.initUndistortRectifyMap(matrix, np.array(dist), None, matrix, (width, height),
                                                       cv2.CV_16SC2)
    return map_xy, map_fraction
