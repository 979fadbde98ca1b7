"""Rendering many textured rectangles with correct occlusion: clipped warps and a z-buffer.

Each face is back-face culled, clipped to the camera's near plane, projected, filled as a
convex polygon mask and warped into the bounding window of that polygon only; a pixel takes
the face when the face's depth there is nearer than what the image holds. The depth of a
plane is exact per pixel: its inverse depth is linear in (u, v), so no interpolation is
needed. Undistorted pinhole cameras only.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from services.geometry.camera import clip_polygon_near
from services.geometry.se3 import transform_points
from services.synthetic.plane import PlaneTexture

Z_NEAR_M = 0.05
SUBPIXEL_BITS = 4


@dataclass(frozen=True)
class Face:
    """A textured rectangle in the world: ``T_world_face`` (4, 4) places its plane frame
    (see ``plane.py``: z is the normal of the visible side)."""

    name: str
    T_world_face: np.ndarray
    texture: PlaneTexture


def render_faces(faces: list[Face], K: np.ndarray, T_cam_world: np.ndarray, size: tuple[int, int],
                 background: int) -> np.ndarray:
    """(size[1], size[0]) uint8 image of ``faces`` seen by pinhole ``K`` at ``T_cam_world``, z-buffered."""
    width, height = size
    image = np.full((height, width), background, np.uint8)
    inverse_depth = np.zeros((height, width), np.float32)
    for face in faces:
        T_cam_face = T_cam_world @ face.T_world_face
        normal, origin = T_cam_face[:3, 2], T_cam_face[:3, 3]
        if normal @ origin >= 0:  # the camera is behind the face's visible side
            continue
        polygon = clip_polygon_near(transform_points(T_cam_face, face.texture.corners()), Z_NEAR_M)
        if len(polygon) < 3:
            continue
        pixels = (polygon @ K.T)[:, :2] / polygon[:, 2:]
        x0, y0 = np.maximum(np.floor(pixels.min(axis=0)).astype(int), 0)
        x1, y1 = np.minimum(np.ceil(pixels.max(axis=0)).astype(int) + 1, (width, height))
        if x0 >= x1 or y0 >= y1:
            continue
        mask = np.zeros((y1 - y0, x1 - x0), np.uint8)
        vertices = np.round((pixels - (x0, y0)) * (1 << SUBPIXEL_BITS)).astype(np.int32)
        cv2.fillConvexPoly(mask, vertices, 1, cv2.LINE_8, SUBPIXEL_BITS)
        # 1/z = (n . K^-1 (u, v, 1)) / (n . t) for the plane n . p = n . t, in camera coordinates
        g = np.linalg.solve(K.T, normal) / (normal @ origin)
        u = np.arange(x0, x1, dtype=np.float32) * np.float32(g[0])
        v = np.arange(y0, y1, dtype=np.float32) * np.float32(g[1]) + np.float32(g[2])
        face_inverse_depth = v[:, None] + u[None, :]
        window = (slice(y0, y1), slice(x0, x1))
        wins = (mask > 0) & (face_inverse_depth > inverse_depth[window])
        warped = face.texture.warp(K, T_cam_face, (x1 - x0, y1 - y0), origin=(int(x0), int(y0)))
        np.copyto(image[window], warped, where=wins)
        np.copyto(inverse_depth[window], face_inverse_depth, where=wins)
    return image
