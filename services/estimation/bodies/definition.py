"""A new rigid body from the sphere centres a rig sees: its frame and its spheres in that frame.

The body frame (``body_frame``): origin at the spheres' centroid; axes along the principal axes of
the centred spheres, x the direction of largest spread, y the second, z = x cross y (right-handed).
Each of x and y points towards the sphere farthest from the centroid along it (the sign whose
largest projection is positive), so the frame depends on the spheres alone, not on their order.
Spheres are listed by increasing x in the body frame.
"""

from __future__ import annotations

import numpy as np

from services.geometry.shapes import check_shape

__all__ = ["body_frame"]


def body_frame(points_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(spheres_body, T_world_body)`` of sphere centres seen in the world.

    ``points_world``: (N, 3) float64, N >= 3, metres, world frame. Returns ``spheres_body``
    (N, 3) float64, the same centres in the body frame above (sorted by x), and ``T_world_body``
    (4, 4), the body frame's pose in the world at the time the points were seen. ValueError for
    fewer than three points or points that are not (N, 3) finite numbers.
    """
    points = check_shape(points_world, "N,3", "points_world", np.float64)
    if not np.isfinite(points).all():
        raise ValueError("points_world must be finite numbers")
    if len(points) < 3:
        raise ValueError(f"a rigid body needs at least 3 spheres, got {len(points)}")
    centroid = points.mean(axis=0)
    centred = points - centroid
    _, _, Vt = np.linalg.svd(centred, full_matrices=False)
    axes = Vt[:2].copy()
    for axis in axes:
        along = centred @ axis
        if along[np.argmax(np.abs(along))] < 0:
            axis *= -1.0
    R_world_body = np.column_stack([axes[0], axes[1], np.cross(axes[0], axes[1])])
    spheres = centred @ R_world_body
    T_world_body = np.eye(4)
    T_world_body[:3, :3], T_world_body[:3, 3] = R_world_body, centroid
    return spheres[np.argsort(spheres[:, 0], kind="stable")], T_world_body
