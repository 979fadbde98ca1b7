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
   (``ambiguity``) is left unmade rather than guessed. A pair whose point a later camera sees
   (in front of it, inside its image) with no blob within the reprojection gate, while that
   camera has a blob within the epipolar gate of one of the pair's blobs, is left unmade for
   now: that camera's blobs, not yet heard, may pair each of the pair's blobs with its own
   sphere's (two spheres each merged in one view leave a blob of each in the other views, and
   the blob of one and that of the other can lie on one epipolar line). Each pair is a new two-view cluster;
3. once every camera has been through, if both blobs of a pair left unmade are still single,
   the blobs still single are paired again, cameras in order, as in 2 but with no pair left
   unmade for a later camera: a sphere hidden from one camera is made from the other two once
   their blobs are known to be wanted by no one else. These pairs are solved together with the
   last camera's pairs, whose blobs they leave alone (a pair of the last camera refused then
   leaves its blobs unpaired);
4. blobs left over stay single (a point needs two views).

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
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, PositiveFloat
from scipy.optimize import linear_sum_assignment

from services.geometry.camera import CameraModel, undistort_pixels
from services.geometry.camera_stack import CameraStack
from services.geometry.epipolar import epipolar_distances, fundamental_matrix
from services.geometry.se3 import invert
from services.geometry.triangulation import TriangulatedPoint, triangulate_dlt_many, triangulate_many

__all__ = ["CorrespondenceOptions", "RigGeometry", "gated_assignment", "unambiguous", "fundamental_matrices",
           "rig_geometry", "triangulate_blobs", "Views"]


class CorrespondenceOptions(BaseModel):
    """How blobs are put in correspondence and triangulated (see the module docstring)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    epipolar_gate_px: float = Field(default=1.5, gt=0, description="largest epipolar distance of a pair, px")
    reprojection_gate_px: float = Field(default=2.0, gt=0, description="largest reprojection error of a view (and "
                                                                       "RMS of a point), px")
    sigma_px: PositiveFloat | Literal["auto"] = Field(
        default="auto", description="centroid noise of the covariances, px; auto: estimated from the points' "
                                    "reprojection residuals over the last sets")
    ambiguity: float = Field(default=0.2, ge=0, description="a pair is left unmade when the best assignment "
                                                            "without it costs less than this much more (in units "
                                                            "of the epipolar gate)")
    min_views: int = Field(default=2, ge=2, description="fewest cameras that must see a point (3 refuses points no "
                                                        "third camera confirms)")

    @property
    def covariance_sigma_px(self) -> float:
        """The centroid noise, per coordinate, the points' covariances are made for: ``sigma_px``, or 1 px
        with ``auto`` (for the caller to scale by its estimate, ``centroid_noise.CentroidNoise``)."""
        return 1.0 if self.sigma_px == "auto" else self.sigma_px


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
    square[np.arange(rows), columns + np.arange(rows)] = gate
    square[rows + np.arange(columns), np.arange(columns)] = gate
    square[rows:, columns:] = 0.0
    chosen_rows, chosen_columns = linear_sum_assignment(square)
    real = (chosen_rows < rows) & (chosen_columns < columns)
    chosen_rows, chosen_columns = chosen_rows[real], chosen_columns[real]
    made = allowed[chosen_rows, chosen_columns]
    return list(zip(chosen_rows[made].tolist(), chosen_columns[made].tolist(), strict=True))


def fundamental_matrices(cameras: Sequence[CameraModel]) -> dict[tuple[int, int], np.ndarray]:
    """``{(b, a): F_b_a}`` for every ordered pair a < b of ``cameras`` (ideal pinhole pixels)."""
    found = {}
    for b, camera_b in enumerate(cameras):
        for a in range(b):
            T_b_a = invert(camera_b.T_rig_camera) @ cameras[a].T_rig_camera
            found[(b, a)] = fundamental_matrix(cameras[a].K, camera_b.K, T_b_a)
    return found


@dataclass(frozen=True)
class RigGeometry:
    """What correspondences need of a set of cameras, made once per calibration: the ``stack`` and
    ``{(b, a): F_b_a}`` (``fundamental_matrices``)."""

    stack: CameraStack
    fundamental: dict[tuple[int, int], np.ndarray]


_RECENT_RIGS: dict[bytes, RigGeometry] = {}
RECENT_RIGS = 8
"""Calibrations whose ``RigGeometry`` is kept (a node's cameras rarely change)."""


def rig_geometry(cameras: Sequence[CameraModel]) -> RigGeometry:
    """The ``RigGeometry`` of ``cameras``, made once for each calibration (keyed by its numbers)."""
    key = b"".join(np.concatenate([np.ravel(c.K), np.ravel(c.dist), np.ravel(c.T_rig_camera)]).astype(np.float64)
                   .tobytes() for c in cameras)
    found = _RECENT_RIGS.get(key)
    if found is None:
        if len(_RECENT_RIGS) >= RECENT_RIGS:
            del _RECENT_RIGS[next(iter(_RECENT_RIGS))]
        found = _RECENT_RIGS[key] = RigGeometry(CameraStack.of(cameras), fundamental_matrices(cameras))
    return found


class Views:
    """One instant's blobs of every camera, stacked once, and the points of clusters of them.

    ``blobs[c]``: (N_c, 2) observed pixels of camera c of ``stack``; ``ideal[c]``: the same undistorted
    (ideal pinhole pixels), for the DLT; None when every point is started from a known position instead
    (``solve``'s ``start``; ``drop_worst`` then starts each point again from where it was). A cluster is
    ``[(camera, blob index)]``, cameras ascending, at least two. The points' covariances are for a
    centroid noise of ``sigma_px``.
    """

    def __init__(self, stack: CameraStack, blobs: Sequence[np.ndarray], ideal: Sequence[np.ndarray] | None,
                 sigma_px: float):
        self.stack, self.blobs, self.sigma_px = stack, blobs, sigma_px
        self.offsets = np.cumsum([0] + [len(b) for b in blobs[:-1]])
        self.every_blob = np.concatenate(blobs)
        self.dlt = ideal is not None
        self.every_ideal = np.concatenate(ideal) if ideal is not None else np.zeros((0, 2))

    def solve(self, clusters: list[list[tuple[int, int]]], start: np.ndarray | None = None) -> list[TriangulatedPoint]:
        """Each cluster's point over all its views (DLT, unless ``start`` (K, 3) has it, then Gauss-Newton), all
        at once."""
        if not clusters:
            return []
        count = len(self.stack)
        pixels = np.zeros((len(clusters), count, 2))
        seen = np.zeros((len(clusters), count), bool)
        rows = [row for row, views in enumerate(clusters) for _ in views]
        cameras_seen, blob_indices = np.array([v for views in clusters for v in views], np.int64).T
        flat = self.offsets[cameras_seen] + blob_indices
        pixels[rows, cameras_seen] = self.every_blob[flat]
        seen[rows, cameras_seen] = True
        undistorted = None
        if start is None:
            if not self.dlt:
                raise ValueError("Views without ideal pixels solve from given start points only")
            undistorted = np.zeros((len(clusters), count, 2))
            undistorted[rows, cameras_seen] = self.every_ideal[flat]
        found = triangulate_many(self.stack, pixels, seen, self.sigma_px, undistorted, start)
        rms = found.rms_px.tolist()
        return [TriangulatedPoint(found.points[row], rms[row], found.covariances[row],
                                  tuple(c for c, _ in views), tuple(i for _, i in views))
                for row, views in enumerate(clusters)]

    def drop_worst(self, clusters: list[list[tuple[int, int]]], solved: list[TriangulatedPoint],
                   gate: float) -> list[TriangulatedPoint]:
        """Each cluster's point (``solved[k]`` of ``clusters[k]``), its worst view dropped and the point solved
        again while one view's reprojection error is above ``gate`` px and more than two remain; ``clusters``
        and ``solved`` are updated in place and ``solved`` returned (a point's RMS may still be above the gate)."""
        count = len(self.stack)
        pending = [k for k in range(len(clusters)) if len(clusters[k]) > 2]
        while pending:
            observed, seen = np.zeros((len(pending), count, 2)), np.zeros((len(pending), count), bool)
            for row, k in enumerate(pending):
                for c, i in clusters[k]:
                    observed[row, c], seen[row, c] = self.blobs[c][i], True
            with np.errstate(invalid="ignore"):
                errors = np.where(seen, np.linalg.norm(self.stack.project(np.array([solved[k].point for k in pending]))
                                                       - observed, axis=2), -np.inf)
                broken = ~(np.max(errors, axis=1) <= gate)
            again = []
            for row in np.flatnonzero(broken).tolist():
                k, worst = pending[row], int(np.argmax(errors[row]))
                clusters[k] = [v for v in clusters[k] if v[0] != worst]
                again.append(k)
            start = None if self.dlt else np.array([solved[k].point for k in again]).reshape(-1, 3)
            for k, point in zip(again, self.solve([clusters[k] for k in again], start), strict=True):
                solved[k] = point
            pending = [k for k in again if len(clusters[k]) > 2]
        return solved


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
    rig = rig_geometry(cameras)
    stack, count = rig.stack, len(cameras)
    instant = Views(stack, blobs, ideal, options.covariance_sigma_px)
    gate = options.reprojection_gate_px
    unmatched = 1.0 + (count - 2)

    size = np.array([[c.width, c.height] for c in cameras], np.float64)

    def offered(c: int, e: int, free: list[int], single_cameras: np.ndarray, single_ideal: np.ndarray,
                rows: np.ndarray, columns: np.ndarray) -> np.ndarray:
        """(K,) bool: whether camera e has a blob within the epipolar gate of blob ``free[rows[k]]`` of camera c or
        of the single blob ``columns[k]`` (of camera ``single_cameras``, ideal pixels ``single_ideal``)."""
        near_free = np.any(epipolar_distances(rig.fundamental[(e, c)], ideal[c][free], ideal[e])
                           < options.epipolar_gate_px, axis=1)
        near_single = np.zeros(len(single_cameras), bool)
        for a in set(single_cameras[columns].tolist()):
            mine = np.flatnonzero(single_cameras == a)
            near_single[mine] = np.any(epipolar_distances(rig.fundamental[(e, a)], single_ideal[mine], ideal[e])
                                       < options.epipolar_gate_px, axis=1)
        return near_free[rows] | near_single[columns]

    def pairing_costs(c: int, free: list[int], single: list[tuple[int, int]]
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(len(free), len(single)) cost of pairing blob ``free[r]`` of camera c with ``single[k]``:
        epipolar distance over its gate, plus for each other camera the distance from the pair's
        point to its nearest blob over the reprojection gate (capped at 1); inf when not allowed.
        Beside it, (len(free), len(single), 3) the pairs' DLT points (NaN where not made) and
        (len(free), len(single)) bool: whether a camera after c sees the pair's point (in front, inside
        its image), has no blob within the reprojection gate of it (the pair unconfirmed) and has one
        within the epipolar gate of either of its blobs (a partner it may offer instead)."""
        cost = np.full((len(free), len(single)), np.inf)
        points_dlt = np.full((len(free), len(single), 3), np.nan)
        unconfirmed = np.zeros((len(free), len(single)), bool)
        if not free or not single:
            return cost, points_dlt, unconfirmed
        distance = np.full((len(free), len(single)), np.inf)
        single_cameras, single_blobs = np.array(single, np.int64).T
        single_ideal = instant.every_ideal[instant.offsets[single_cameras] + single_blobs]
        for a in set(single_cameras.tolist()):
            columns = np.flatnonzero(single_cameras == a)
            distance[:, columns] = epipolar_distances(rig.fundamental[(c, a)], single_ideal[columns],
                                                      ideal[c][free]).T
        rows, columns = np.nonzero(distance < options.epipolar_gate_px)
        if not len(rows):
            return cost, points_dlt, unconfirmed
        undistorted = np.zeros((len(rows), count, 2))
        seen = np.zeros((len(rows), count), bool)
        pair_cameras = single_cameras[columns]
        undistorted[np.arange(len(rows)), pair_cameras] = single_ideal[columns]
        undistorted[:, c] = ideal[c][np.asarray(free)[rows]]
        seen[np.arange(len(rows)), pair_cameras] = True
        seen[:, c] = True
        points = points_dlt[rows, columns] = triangulate_dlt_many(stack.projections, undistorted, seen)
        with np.errstate(invalid="ignore"):
            depths = stack.depths(points)
            in_front = np.all((depths > 0.0) | ~seen, axis=1) & np.all(np.isfinite(points), axis=1)
        support = np.zeros(len(rows))
        if count > 2:
            projected = stack.project(points)
            with np.errstate(invalid="ignore"):
                sees = (depths > 0.0) & np.all((projected >= 0.0) & (projected <= size - 1.0), axis=2)
            for e in range(count):
                others = ~seen[:, e]
                if not np.any(others):
                    continue
                near = np.ones(len(rows))
                if len(blobs[e]):
                    gaps = np.linalg.norm(projected[:, e, None, :] - blobs[e][None], axis=2).min(axis=1) / gate
                    near = np.where(np.isfinite(gaps), np.minimum(gaps, 1.0), 1.0)
                support += np.where(others, near, 0.0)
                lonely = sees[:, e] & (near >= 1.0)
                if e > c and len(blobs[e]) and np.any(lonely):
                    unconfirmed[rows, columns] |= lonely & offered(c, e, free, single_cameras, single_ideal,
                                                                   rows, columns)
        cost[rows[in_front], columns[in_front]] = (distance[rows, columns] / options.epipolar_gate_px
                                                   + support)[in_front]
        return cost, points_dlt, unconfirmed

    Pair = list[tuple[int, int]]

    def choose(c: int, free: list[int], single: list[tuple[int, int]], defer: bool
               ) -> tuple[list[Pair], np.ndarray, list[Pair]]:
        """The pairs of the ``free`` blobs of camera c with the ``single`` blobs of earlier cameras (module docstring),
        those a later camera leaves unconfirmed left unmade with ``defer``: ``[(camera, blob), (c, blob)]`` each, their
        (K, 3) DLT points, and the pairs that could be made and were left unmade."""
        cost, points_dlt, unconfirmed = pairing_costs(c, free, single)
        rows, columns = np.nonzero(unconfirmed & (cost < unmatched)) if defer else ((), ())
        deferred = [[single[k], (c, free[r])] for r, k in zip(rows, columns, strict=True)]
        if deferred:
            cost[unconfirmed] = np.inf
        pairs = unambiguous(gated_assignment(cost, unmatched), cost, unmatched, options.ambiguity)
        return ([[single[column], (c, free[row])] for row, column in pairs],
                points_dlt[tuple(np.array(pairs, np.int64).reshape(-1, 2).T)], deferred)

    def make(pairs: list[Pair], points_dlt: np.ndarray) -> list[Pair]:
        """The ``pairs`` whose point, solved from its (K, 3) DLT point, is in front of both cameras with its RMS within
        the gate, each appended to ``clusters`` and its point to ``solved``."""
        made = instant.solve(pairs, points_dlt)
        depths = stack.depths(np.array([p.point for p in made]).reshape(-1, 3))
        kept = []
        for k, (views, point) in enumerate(zip(pairs, made, strict=True)):
            if point.rms_px <= gate and depths[k, views[0][0]] > 0.0 and depths[k, views[1][0]] > 0.0:
                clusters.append(views)
                solved.append(point)
                kept.append(views)
        return kept

    def left_single(single: list[tuple[int, int]], c: int, free: list[int], pairs: list[Pair]
                    ) -> list[tuple[int, int]]:
        """``single`` less the blobs of ``pairs``, then the ``free`` blobs of camera c in none of them."""
        paired = {view for views in pairs for view in views}
        return [s for s in single if s not in paired] + [(c, i) for i in free if (c, i) not in paired]

    clusters: list[list[tuple[int, int]]] = []
    solved: list[TriangulatedPoint] = []
    single: list[tuple[int, int]] = [(0, i) for i in range(len(blobs[0]))]
    deferred: list[Pair] = []
    last: list[Pair] = []
    last_dlt = np.zeros((0, 3))
    for c in range(1, count):
        taken: set[int] = set()
        if clusters and len(blobs[c]):
            projected = stack.project(np.array([p.point for p in solved]))[:, c]
            cost = np.linalg.norm(projected[:, None, :] - blobs[c][None, :, :], axis=2)
            grown = gated_assignment(cost, gate)
            for k, i in grown:
                clusters[k].append((c, i))
                taken.add(i)
            for (k, _), point in zip(grown, instant.solve([clusters[k] for k, _ in grown]), strict=True):
                solved[k] = point
        free = [i for i in range(len(blobs[c])) if i not in taken]
        pairs, points_dlt, later = choose(c, free, single, defer=c < count - 1)
        deferred += later
        if c < count - 1:
            pairs = make(pairs, points_dlt)
        else:
            last, last_dlt = pairs, points_dlt
        single = left_single(single, c, free, pairs)
    if any(first in single and second in single for first, second in deferred):
        # A pair left unmade for a later camera's sake, which took neither blob: the blobs left paired again, the
        # pairs solved with the last camera's.
        left, single = single, [s for s in single if s[0] == 0]
        for c in range(1, count):
            free = [i for camera, i in left if camera == c]
            pairs, points_dlt, _ = choose(c, free, single, defer=False)
            last, last_dlt = last + pairs, np.concatenate([last_dlt, points_dlt])
            single = left_single(single, c, free, pairs)
    make(last, last_dlt)
    return [p for p in instant.drop_worst(clusters, solved, gate)
            if p.rms_px <= gate and p.views >= options.min_views]


def unambiguous(matches: list[tuple[int, int]], cost: np.ndarray, unmatched: float,
                margin: float) -> list[tuple[int, int]]:
    """The ``matches`` of ``gated_assignment(cost, unmatched)`` whose removal raises the total
    cost by at least ``margin``: a match that a different assignment explains almost as well
    (two blobs on one epipolar line, say) is dropped rather than guessed."""
    def total(found: list[tuple[int, int]], table: np.ndarray) -> float:
        rows, columns = table.shape
        return float(sum(table[r, k] for r, k in found) + unmatched * (rows + columns - 2 * len(found)))

    best = total(matches, cost)
    allowed = np.isfinite(cost) & (cost < unmatched)
    alone = (allowed.sum(axis=1)[:, None] == 1) & (allowed.sum(axis=0)[None, :] == 1)
    kept = []
    for row, column in matches:
        if alone[row, column]:
            # Neither blob has another partner: without this match both stay unmatched, the rest unchanged.
            if 2.0 * unmatched - cost[row, column] >= margin:
                kept.append((row, column))
            continue
        without = cost.copy()
        without[row, column] = np.inf
        if total(gated_assignment(without, unmatched), without) - best >= margin:
            kept.append((row, column))
    return kept
