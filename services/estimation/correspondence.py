"""Which blobs of N >= 2 calibrated cameras are one sphere: correspondences, then 3D points.

World = the rig frame (the cameras' ``T_rig_camera``). Blobs are (N_c, 2) observed pixel
centroids per camera (with the camera's distortion). Cameras are taken in order; after
camera c, every blob of cameras 0..c belongs to exactly one cluster:

1. the clusters that already have a 3D point (two views or more) take blobs of camera c by
   a global assignment (``linear_sum_assignment``) on the reprojection distance, gated;
2. the blobs of camera c still free are paired with the free blobs of earlier cameras by a
   second global assignment; a pair is allowed under the epipolar gate (undistorted pixels)
   with its point in front of both cameras, and costs its epipolar distance (over the gate)
   plus, for every other camera, the distance from the pair's point to that camera's nearest
   blob (over the reprojection gate, at most 1): a third camera's blob confirms the right
   pairing where two blobs lie on one epipolar line, while a point no other camera sees
   (occluded) can still be made. A pair that another assignment explains almost as well
   (``ambiguity``) is left unmade rather than guessed. Each pair is a new two-view cluster;
3. blobs left over stay single (a point needs two views).

Unmatched rows and columns cost the most a match may cost, so a match is made only when it
lowers the total: blobs go to the pairing that explains all of them best, not to whichever
comes first, and no blob is used twice. Finally each cluster is refined over all its views;
a view whose residual breaks the reprojection gate is dropped (the worst first) while more
than two remain, and the point is kept if its RMS is within the gate and it has
``min_views`` views.

With two cameras, two spheres on one epipolar plane cannot be told apart from their blobs
alone: both are left out. Two spurious blobs near one epipolar line make a phantom point
unless ``min_views`` is 3.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment

from services.geometry.camera import CameraModel, undistort_pixels
from services.geometry.epipolar import epipolar_distances, fundamental_matrix
from services.geometry.se3 import invert
from services.geometry.triangulation import (
    TriangulatedPoint,
    projection_matrix,
    reproject,
    triangulate,
    triangulate_dlt,
)

__all__ = ["CorrespondenceOptions", "gated_assignment", "unambiguous", "fundamental_matrices", "triangulate_blobs"]


@dataclass(frozen=True)
class CorrespondenceOptions:
    """``epipolar_gate_px``: largest epipolar distance of a pair; ``reprojection_gate_px``: largest
    reprojection error of a view (and RMS of a point); ``sigma_px``: centroid noise, per
    coordinate, for the covariances; ``ambiguity``: a pair is left unmade when the best
    assignment without it costs less than this much more (in units of the epipolar gate);
    ``min_views``: fewest views of a point kept (2; 3 refuses points no third camera confirms)."""

    epipolar_gate_px: float = 1.5
    reprojection_gate_px: float = 2.0
    sigma_px: float = 0.1
    ambiguity: float = 0.2
    min_views: int = 2


def gated_assignment(cost: np.ndarray, gate: float) -> list[tuple[int, int]]:
    """``[(row, column)]`` of the one-to-one assignment of least total cost in which any row or
    column may stay unmatched at a cost of ``gate``; only entries below ``gate`` can be matched.

    ``cost``: (R, C), NaN or inf for pairs that cannot match.
    """
    cost = np.asarray(cost, dtype=np.float64)
    rows, columns = cost.shape
    if rows == 0 or columns == 0:
        return []
    forbidden = 2.0 * gate * (rows + columns) + 1.0
    allowed = np.isfinite(cost) & (cost < gate)
    square = np.full((rows + columns, columns + rows), forbidden)
    square[:rows, :columns] = np.where(allowed, cost, forbidden)
    square[:rows, columns:] = np.where(np.eye(rows, dtype=bool), gate, forbidden)
    square[rows:, :columns] = np.where(np.eye(columns, dtype=bool), gate, forbidden)
    square[rows:, columns:] = 0.0
    chosen_rows, chosen_columns = linear_sum_assignment(square)
    return [(int(r), int(c)) for r, c in zip(chosen_rows, chosen_columns, strict=True)
            if r < rows and c < columns and allowed[r, c]]


def fundamental_matrices(cameras: Sequence[CameraModel]) -> dict[tuple[int, int], np.ndarray]:
    """``{(b, a): F_b_a}`` for every ordered pair a < b of ``cameras`` (ideal pinhole pixels)."""
    found = {}
    for b, camera_b in enumerate(cameras):
        for a in range(b):
            T_b_a = invert(camera_b.T_rig_camera) @ cameras[a].T_rig_camera
            found[(b, a)] = fundamental_matrix(cameras[a].K, camera_b.K, T_b_a)
    return found


def _in_front(camera: CameraModel, point: np.ndarray) -> bool:
    T_camera_world = invert(camera.T_rig_camera)
    return float(T_camera_world[2, :3] @ point + T_camera_world[2, 3]) > 0.0


def triangulate_blobs(cameras: Sequence[CameraModel], blobs: Sequence[np.ndarray],
                      options: CorrespondenceOptions | None = None) -> list[TriangulatedPoint]:
    """3D points, world (rig) frame, from the blobs of every camera (see the module docstring).

    ``cameras``: N >= 2 calibrated cameras; ``blobs[c]``: (N_c, 2) observed pixels of camera c.
    Each point's ``camera_indices`` / ``blob_indices`` name the blobs it was made from.
    """
    options = options or CorrespondenceOptions()
    if len(cameras) < 2 or len(blobs) != len(cameras):
        raise ValueError(f"triangulate_blobs needs blobs for each of >= 2 cameras, got {len(cameras)} cameras "
                         f"and {len(blobs)} blob lists")
    blobs = [np.asarray(b, dtype=np.float64).reshape(-1, 2) for b in blobs]
    ideal = [undistort_pixels(b, c.K, c.dist) for c, b in zip(cameras, blobs, strict=True)]
    F = fundamental_matrices(cameras)
    projections = np.array([projection_matrix(c.K, invert(c.T_rig_camera)) for c in cameras])
    gate = options.reprojection_gate_px

    def solve(views: list[tuple[int, int]]) -> TriangulatedPoint:
        return triangulate([cameras[c] for c, _ in views], np.array([blobs[c][i] for c, i in views]),
                           options.sigma_px, [c for c, _ in views], [i for _, i in views])

    def final(views: list[tuple[int, int]]) -> TriangulatedPoint | None:
        """The cluster's point over all its views, the worst view dropped while one breaks the
        gate and more than two remain; None when the RMS of what is left is above the gate."""
        point = solve(views)
        while len(views) > 2:
            errors = [float(np.linalg.norm(reproject(cameras[c], point.point)[0] - blobs[c][i])) for c, i in views]
            if max(errors) <= gate:
                break
            views = [v for k, v in enumerate(views) if k != int(np.argmax(errors))]
            point = solve(views)
        return point if point.rms_px <= gate else None

    unmatched = 1.0 + (len(cameras) - 2)

    def pairing_costs(c: int, free: list[int], single: list[tuple[int, int]]) -> np.ndarray:
        """(len(free), len(single)) cost of pairing blob ``free[r]`` of camera c with ``single[k]``:
        epipolar distance over its gate, plus for each other camera the distance from the pair's
        point to its nearest blob over the reprojection gate (capped at 1); inf when not allowed."""
        cost = np.full((len(free), len(single)), np.inf)
        if not free:
            return cost
        for column, (a, j) in enumerate(single):
            distance = epipolar_distances(F[(c, a)], ideal[a][j:j + 1], ideal[c][free])[0]
            for row in np.flatnonzero(distance < options.epipolar_gate_px):
                try:
                    point = triangulate_dlt(projections[[a, c]], np.array([ideal[a][j], ideal[c][free[row]]]))
                except ValueError:
                    continue
                if not (_in_front(cameras[a], point) and _in_front(cameras[c], point)):
                    continue
                support = sum(nearest(reproject(cameras[e], point)[0], blobs[e]) for e in range(len(cameras))
                              if e not in (a, c))
                cost[row, column] = distance[row] / options.epipolar_gate_px + support
        return cost

    def nearest(pixel: np.ndarray, observed: np.ndarray) -> float:
        """Distance from ``pixel`` to the nearest of (M, 2) ``observed`` over the reprojection gate, at most 1."""
        if len(observed) == 0 or not np.all(np.isfinite(pixel)):
            return 1.0
        return min(float(np.min(np.linalg.norm(observed - pixel, axis=1))) / gate, 1.0)

    clusters: list[list[tuple[int, int]]] = []
    points: list[np.ndarray] = []
    single: list[tuple[int, int]] = [(0, i) for i in range(len(blobs[0]))]
    for c in range(1, len(cameras)):
        taken: set[int] = set()
        if clusters and len(blobs[c]):
            projected = reproject(cameras[c], np.array(points))
            cost = np.linalg.norm(projected[:, None, :] - blobs[c][None, :, :], axis=2)
            for k, i in gated_assignment(cost, gate):
                clusters[k].append((c, i))
                points[k] = solve(clusters[k]).point
                taken.add(i)
        free = [i for i in range(len(blobs[c])) if i not in taken]
        cost = pairing_costs(c, free, single)
        used: set[int] = set()
        for row, column in unambiguous(gated_assignment(cost, unmatched), cost, unmatched, options.ambiguity):
            views = [single[column], (c, free[row])]
            point = solve(views)
            if point.rms_px <= gate and all(_in_front(cameras[v], point.point) for v, _ in views):
                clusters.append(views)
                points.append(point.point)
                used.add(column)
                taken.add(free[row])
        single = [s for column, s in enumerate(single) if column not in used]
        single += [(c, i) for i in range(len(blobs[c])) if i not in taken]
    return [p for p in map(final, clusters) if p is not None and p.views >= options.min_views]


def unambiguous(matches: list[tuple[int, int]], cost: np.ndarray, unmatched: float,
                margin: float) -> list[tuple[int, int]]:
    """The ``matches`` of ``gated_assignment(cost, unmatched)`` whose removal raises the total
    cost by at least ``margin``: a match that a different assignment explains almost as well
    (two blobs on one epipolar line, say) is dropped rather than guessed."""
    def total(found: list[tuple[int, int]], table: np.ndarray) -> float:
        rows, columns = table.shape
        return float(sum(table[r, k] for r, k in found) + unmatched * (rows + columns - 2 * len(found)))

    best = total(matches, cost)
    kept = []
    for row, column in matches:
        without = cost.copy()
        without[row, column] = np.inf
        if total(gated_assignment(without, unmatched), without) - best >= margin:
            kept.append((row, column))
    return kept
