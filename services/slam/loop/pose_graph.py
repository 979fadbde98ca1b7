"""Pose-graph optimisation in Sim(3): keyframe poses moved to agree with relative measurements.

Nodes: keyframe id -> ``S_camera_world`` (4, 4) similarity (``sim3``; a keyframe's rigid pose is one of
scale 1). Edges ``(i, j, S_ij)``: node ``i``'s camera from node ``j``'s camera as measured, (4, 4). An
edge's residual (7,) is the log of its error ``E = S_ij^-1 S_i S_j^-1`` (the identity when the nodes agree
with it): the rotation vector of ``E``'s rotation (rad), its translation (map units) and the log of its
scale, all weighed alike (ORB-SLAM's essential graph uses identity information).

Each free node's unknown is a left increment ``(w, v, sigma)`` (7,) of its start: ``S_i = D S_i_start``
with ``D`` the similarity of scale ``exp(sigma)``, rotation ``exp([w]x)`` and translation ``v``. Fixed nodes
(at least one: the gauge, seven degrees of freedom) keep their start. Solved by
``scipy.optimize.least_squares`` (trust region, finite differences over the Jacobian's sparsity: each
edge's seven residuals depend on its two nodes' increments only).
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import lil_matrix
from scipy.spatial.transform import Rotation

__all__ = ["Edge", "PoseGraphResult", "edge_residuals", "optimise_pose_graph"]

Edge = tuple[int, int, np.ndarray]
"""``(i, j, S_ij)``: node ``i``'s camera from node ``j``'s, (4, 4) similarity."""


class PoseGraphResult:
    """``poses`` node id -> optimised ``S_camera_world`` (4, 4); ``initial_cost`` and ``final_cost``: half
    the sum of squared residuals before and after; ``evaluations`` of the residuals."""

    def __init__(self, poses: dict[int, np.ndarray], initial_cost: float, final_cost: float, evaluations: int):
        self.poses = poses
        self.initial_cost = initial_cost
        self.final_cost = final_cost
        self.evaluations = evaluations


def _increments(x: np.ndarray) -> np.ndarray:
    """(F, 4, 4) the similarities of (F * 7,) increments ``(w, v, sigma)`` per node."""
    x = x.reshape(-1, 7)
    D = np.tile(np.eye(4), (len(x), 1, 1))
    D[:, :3, :3] = np.exp(x[:, 6])[:, None, None] * Rotation.from_rotvec(x[:, :3]).as_matrix()
    D[:, :3, 3] = x[:, 3:6]
    return D


def _log(E: np.ndarray) -> np.ndarray:
    """(M, 7) ``(rotation vector, translation, log scale)`` of (M, 4, 4) similarities."""
    scale = np.cbrt(np.linalg.det(E[:, :3, :3]))
    rotvec = Rotation.from_matrix(E[:, :3, :3] / scale[:, None, None]).as_rotvec()
    return np.concatenate([rotvec, E[:, :3, 3], np.log(scale)[:, None]], axis=1)


def edge_residuals(poses: np.ndarray, first: np.ndarray, second: np.ndarray,
                   measured_inverse: np.ndarray) -> np.ndarray:
    """(M, 7) residuals of M edges between rows ``first`` and ``second`` (M,) of ``poses`` (F, 4, 4)
    ``S_camera_world``, ``measured_inverse`` (M, 4, 4) the inverses of their measurements."""
    E = measured_inverse @ poses[first] @ np.linalg.inv(poses[second])
    return _log(E)


def optimise_pose_graph(poses: dict[int, np.ndarray], edges: list[Edge], fixed: set[int],
                        max_evaluations: int = 100) -> PoseGraphResult:
    """Nodes ``poses`` (id -> start ``S_camera_world`` (4, 4)) moved to fit ``edges`` (module docstring);
    those in ``fixed`` stay. ValueError when no node is fixed or an edge names an unknown node."""
    ids = sorted(poses)
    row = {k: r for r, k in enumerate(ids)}
    if not fixed & set(ids):
        raise ValueError("a pose graph needs a fixed node (the gauge)")
    unknown = {k for i, j, _ in edges for k in (i, j) if k not in row}
    if unknown:
        raise ValueError(f"edges name nodes without a pose: {sorted(unknown)[:5]}")
    start = np.array([poses[k] for k in ids], np.float64)
    free = np.array([k not in fixed for k in ids])
    slot = np.cumsum(free) - 1
    first = np.array([row[i] for i, _, _ in edges], np.int64)
    second = np.array([row[j] for _, j, _ in edges], np.int64)
    measured_inverse = np.linalg.inv(np.array([S for _, _, S in edges], np.float64).reshape(-1, 4, 4))

    def moved(x: np.ndarray) -> np.ndarray:
        current = start.copy()
        current[free] = _increments(x) @ start[free]
        return current

    def residuals(x: np.ndarray) -> np.ndarray:
        return edge_residuals(moved(x), first, second, measured_inverse).ravel()

    count = int(free.sum())
    if count == 0 or not edges:
        return PoseGraphResult(dict(poses), 0.0, 0.0, 0)
    sparsity = lil_matrix((7 * len(edges), 7 * count), dtype=np.int8)
    for e, (a, b) in enumerate(zip(first.tolist(), second.tolist(), strict=True)):
        for node in (a, b):
            if free[node]:
                sparsity[7 * e:7 * e + 7, 7 * slot[node]:7 * slot[node] + 7] = 1
    x0 = np.zeros(7 * count)
    initial = 0.5 * float(np.sum(residuals(x0) ** 2))
    solved = least_squares(residuals, x0, jac_sparsity=sparsity, method="trf", tr_solver="lsmr",
                           max_nfev=max_evaluations, x_scale=1.0)
    final = moved(solved.x)
    return PoseGraphResult({k: final[r] for k, r in row.items()}, initial, float(solved.cost), int(solved.nfev))
