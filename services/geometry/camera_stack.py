"""Several calibrated cameras as stacked arrays: world points projected into all of them at once.

World = the frame the cameras' ``T_rig_camera`` poses are given in (a rig's frame). The model is
OpenCV's pinhole with plumb_bob distortion (k1, k2, p1, p2, k3), as ``cv2.projectPoints`` applies
it (``fx``, ``fy``, ``cx``, ``cy`` of K; its skew is ignored), written out so that N points and
C cameras cost a few array operations, with the derivatives of the pixels with respect to the
world point in closed form.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from services.geometry.camera import CameraModel
from services.geometry.shapes import check_shape

__all__ = ["CameraStack"]


@dataclass(frozen=True)
class CameraStack:
    """C cameras: ``K`` (C, 3, 3), ``dist`` (C, 5) plumb_bob, ``R_camera_world`` (C, 3, 3) and
    ``t_camera_world`` (C, 3) (world into each camera's frame), ``projections`` (C, 3, 4)
    ``K [R | t]`` (homogeneous world points to ideal pinhole pixels)."""

    K: np.ndarray
    dist: np.ndarray
    R_camera_world: np.ndarray
    t_camera_world: np.ndarray
    projections: np.ndarray

    @classmethod
    def of(cls, cameras: Sequence[CameraModel]) -> CameraStack:
        """The stack of ``cameras`` in their order; ValueError for a distortion beyond plumb_bob's five terms."""
        dist = np.zeros((len(cameras), 5))
        for row, camera in enumerate(cameras):
            coefficients = np.asarray(camera.dist, dtype=np.float64).ravel()
            if len(coefficients) > 5 and np.any(coefficients[5:]):
                raise ValueError(f"camera {camera.name}: {len(coefficients)} distortion terms, plumb_bob has 5")
            dist[row, :min(len(coefficients), 5)] = coefficients[:5]
        K = np.array([np.asarray(c.K, dtype=np.float64) for c in cameras]).reshape(-1, 3, 3)
        R_world_camera = np.array([np.asarray(c.T_rig_camera, dtype=np.float64)[:3, :3] for c in cameras])
        centres = np.array([np.asarray(c.T_rig_camera, dtype=np.float64)[:3, 3] for c in cameras])
        R = R_world_camera.reshape(-1, 3, 3).transpose(0, 2, 1)
        t = -np.einsum("cij,cj->ci", R, centres.reshape(-1, 3))
        projections = K @ np.concatenate([R, t[:, :, None]], axis=2)
        return cls(K, dist, R, t, projections)

    def __len__(self) -> int:
        return len(self.K)

    def to_cameras(self, points_world: np.ndarray) -> np.ndarray:
        """(N, C, 3) each camera's frame coordinates of (N, 3) world points."""
        points_world = check_shape(points_world, "*,3", "points_world", np.float64).reshape(-1, 3)
        return np.einsum("cij,nj->nci", self.R_camera_world, points_world) + self.t_camera_world

    def depths(self, points_world: np.ndarray) -> np.ndarray:
        """(N, C) depth (camera z, m) of (N, 3) world points in each camera."""
        points_world = check_shape(points_world, "*,3", "points_world", np.float64).reshape(-1, 3)
        return points_world @ self.R_camera_world[:, 2, :].T + self.t_camera_world[:, 2]

    def project(self, points_world: np.ndarray) -> np.ndarray:
        """(N, C, 2) observed pixels (through the distortion) of (N, 3) world points; NaN at depths <= 0."""
        with np.errstate(divide="ignore", invalid="ignore"):
            pixels, _ = self._project(points_world, False)
        pixels[self.depths(points_world) <= 0.0] = np.nan
        return pixels

    def project_with_jacobians(self, points_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(pixels (N, C, 2), jacobians (N, C, 2, 3))``: as ``project``, with the pixels' derivatives
        with respect to the world point (px/m); a point behind a camera is projected through it as
        ``cv2.projectPoints`` does (no NaN)."""
        pixels, jacobians = self._project(points_world, True)
        assert jacobians is not None
        return pixels, jacobians

    @cached_property
    def _distortion(self) -> tuple[np.ndarray, ...]:
        """(C,) ``k1, k2, p1, p2, k3`` of every camera."""
        return tuple(self.dist[:, k] for k in range(5))

    @cached_property
    def _intrinsics(self) -> tuple[np.ndarray, ...]:
        """(C,) ``fx, fy, cx, cy`` of every camera."""
        return self.K[:, 0, 0], self.K[:, 1, 1], self.K[:, 0, 2], self.K[:, 1, 2]

    def _project(self, points_world: np.ndarray, with_jacobians: bool) -> tuple[np.ndarray, np.ndarray | None]:
        p = self.to_cameras(points_world)
        inverse_z = 1.0 / p[..., 2]
        x, y = p[..., 0] * inverse_z, p[..., 1] * inverse_z
        k1, k2, p1, p2, k3 = self._distortion
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xy = x * y
        xd = x * radial + 2.0 * p1 * xy + p2 * (r2 + 2.0 * x * x)
        yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * xy
        fx, fy, cx, cy = self._intrinsics
        pixels = np.stack([fx * xd + cx, fy * yd + cy], axis=-1)
        if not with_jacobians:
            return pixels, None
        d_radial = k1 + r2 * (2.0 * k2 + 3.0 * r2 * k3)  # d radial / d r2
        cross = 2.0 * xy * d_radial + 2.0 * p1 * x + 2.0 * p2 * y
        d_distorted = np.empty(p.shape[:2] + (2, 2))  # d (xd, yd) / d (x, y)
        d_distorted[..., 0, 0] = radial + 2.0 * x * x * d_radial + 2.0 * p1 * y + 6.0 * p2 * x
        d_distorted[..., 0, 1] = cross
        d_distorted[..., 1, 0] = cross
        d_distorted[..., 1, 1] = radial + 2.0 * y * y * d_radial + 6.0 * p1 * y + 2.0 * p2 * x
        d_distorted[..., 0, :] *= fx[:, None]
        d_distorted[..., 1, :] *= fy[:, None]
        d_normalised = np.zeros(p.shape[:2] + (2, 3))  # d (x, y) / d camera point
        d_normalised[..., 0, 0] = inverse_z
        d_normalised[..., 1, 1] = inverse_z
        d_normalised[..., 0, 2] = -x * inverse_z
        d_normalised[..., 1, 2] = -y * inverse_z
        jacobians = d_distorted @ d_normalised @ self.R_camera_world
        return pixels, jacobians
