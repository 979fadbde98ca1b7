"""Textured planar rectangles and their perspective rendering with cv2.warpPerspective.

A plane's frame: origin at the rectangle's centre, x right, y up, z out of the textured
face (towards a viewer who sees the texture upright), as OpenCV's ArUco marker frame.
The texture covers ``|x| <= width_m / 2``, ``|y| <= height_m / 2``; its pixel (0, 0) is the
top-left one (x = -width_m / 2, y = +height_m / 2 corner).

Minification is handled with a mip pyramid (cv2.pyrDown, which maps texel coordinates
exactly by 1/2 per level): each warp samples the level whose texel roughly matches one
image pixel at a reference pixel, so small and oblique views neither alias nor shimmer.
"""

from __future__ import annotations

import cv2
import numpy as np

from services.geometry.camera import plane_homography

MIN_LEVEL_SIDE = 16


def rectangle_corners(width_m: float, height_m: float) -> np.ndarray:
    """(4, 3) corners of a rectangle centred in its plane frame, in ArUco order: TL, TR, BR, BL."""
    x, y = width_m / 2, height_m / 2
    return np.array([[-x, y, 0.0], [x, y, 0.0], [x, -y, 0.0], [-x, -y, 0.0]])


def texel_from_plane(shape: tuple[int, ...], width_m: float, height_m: float) -> np.ndarray:
    """(3, 3): plane (x, y, 1) in metres -> texel (u, v, 1), pixel centres at integers, for a texture
    image of ``shape`` (h, w[, c]) covering ``width_m`` x ``height_m``."""
    h, w = shape[:2]
    sx, sy = w / width_m, h / height_m
    return np.array([[sx, 0.0, sx * width_m / 2 - 0.5], [0.0, -sy, sy * height_m / 2 - 0.5], [0.0, 0.0, 1.0]])


class PlaneTexture:
    """A (h, w) uint8 ``image`` covering a ``width_m`` x ``height_m`` rectangle of a plane.

    ``levels``: its mip pyramid, ``levels[0]`` the image itself.
    """

    def __init__(self, image: np.ndarray, width_m: float, height_m: float):
        self.width_m, self.height_m = float(width_m), float(height_m)
        self.levels = [image]
        while min(self.levels[-1].shape[:2]) >= 2 * MIN_LEVEL_SIDE:
            self.levels.append(cv2.pyrDown(self.levels[-1]))
        self.texel_from_plane = texel_from_plane(image.shape, self.width_m, self.height_m)

    def corners(self) -> np.ndarray:
        """(4, 3) corners of the textured rectangle in the plane frame (see ``rectangle_corners``)."""
        return rectangle_corners(self.width_m, self.height_m)

    def image_from_texel(self, K: np.ndarray, T_cam_plane: np.ndarray) -> np.ndarray:
        """(3, 3) homography: level-0 texel (u, v, 1) -> pixel, undistorted pinhole ``K``."""
        return plane_homography(K, T_cam_plane) @ np.linalg.inv(self.texel_from_plane)

    def level_at(self, image_from_texel: np.ndarray, pixel: tuple[float, float]) -> int:
        """Pyramid level whose texels are closest to one image pixel in area, at ``pixel``."""
        G = np.linalg.inv(image_from_texel)
        q = G @ np.array([pixel[0], pixel[1], 1.0])
        J = (G[:2, :2] - np.outer(q[:2] / q[2], G[2, :2])) / q[2]
        texels_per_pixel = np.sqrt(abs(np.linalg.det(J)))
        level = int(round(np.log2(max(texels_per_pixel, 1e-12))))
        return min(max(level, 0), len(self.levels) - 1)

    def warp(self, K: np.ndarray, T_cam_plane: np.ndarray, size: tuple[int, int], origin: tuple[int, int] = (0, 0),
             border_value: int | None = None) -> np.ndarray:
        """The plane seen by camera ``K`` at ``T_cam_plane``: (size[1], size[0]) uint8.

        The output is the image window whose top-left pixel is ``origin`` (x, y); outside
        the texture it shows ``border_value``, or the texture's edge texels when None.
        Points behind the camera are not clipped: callers mask them (or keep the plane in front).
        """
        image_from_texel = self.image_from_texel(K, T_cam_plane)
        level = self.level_at(image_from_texel, (origin[0] + (size[0] - 1) / 2, origin[1] + (size[1] - 1) / 2))
        scale = 2.0 ** level
        window_from_level = (np.array([[1.0, 0.0, -origin[0]], [0.0, 1.0, -origin[1]], [0.0, 0.0, 1.0]])
                             @ image_from_texel @ np.diag([scale, scale, 1.0]))
        mode = cv2.BORDER_REPLICATE if border_value is None else cv2.BORDER_CONSTANT
        return cv2.warpPerspective(self.levels[level], window_from_level, size, flags=cv2.INTER_LINEAR,
                                   borderMode=mode, borderValue=border_value or 0)
