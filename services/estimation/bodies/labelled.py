"""Bodies followed in the images: the blobs labelled by each predicted body's spheres, triangulated and fitted
without a search; the other blobs through the full path.

World = the rig frame. Blobs are (N_c, 2) observed pixel centroids per camera (with its distortion). Per
instant, given a predicted ``T_world_body`` (4, 4) for some bodies (``tracking.BodyTracker.forecast``):

1. ``label_blobs``: every predicted sphere's world position is projected into every camera, through the
   distortion (compiled: ``label_kernel.label``). Per camera, the blobs are assigned one-to-one to the
   projected spheres of all predicted bodies together (least total pixel distance, each pair closer than
   ``gate_px``: ``correspondence.gated_assignment``). A blob within ``gate_px`` of two predicted spheres or
   more (their images merged, or about to) is doubtful: none of those spheres takes a view in that camera
   (each keeps its others), and the blob is left to the full path. A blob far from every predicted sphere
   (a stray, a body lost or new) is never labelled. ``label_parts`` then gives the two parts of a blob split
   in two discs (``detection.blobs.split``: the centres of two spheres merged in that view) to the two
   predicted spheres inside it, one each (the pairing of least total distance, each within ``gate_px``),
   where exactly two predicted spheres lie within ``gate_px`` of the parts and neither has a view in that
   camera yet.
2. ``triangulate_labelled``: a sphere labelled in two cameras or more is triangulated over all its views,
   every sphere in one batch (``correspondence.Views``: Gauss-Newton from the sphere's predicted position and
   covariance, the worst view dropped while one breaks the reprojection gate and more than two remain): the
   point, residual and covariance ``triangulate_blobs`` gives a cluster of the same views from its DLT (the
   same minimum, to 1e-10 m), with no undistortion nor DLT for the labelled blobs. A point whose RMS is above the gate,
   or with fewer than ``min_views`` views, is left out. So a part that lies off its sphere's other views
   is the view dropped, and a sphere seen cleanly by two cameras keeps them whatever a third makes of it.
3. ``track_blobs``: each predicted body is fitted to its labelled points (``rigid.fit_labelled``: no search,
   the worst sphere let go while the fit breaks its gate, ``rigid.within_gates``; at least ``min_spheres``
   kept). The blobs in no point kept, the split blobs' parts among them, are put in correspondence by
   ``triangulate_blobs``; the bodies not fitted are then looked for among those points and the labelled
   points no fit kept, near their prediction first, else by their distance signatures
   (``tracking.match_with_prediction``). A decoy repeating a body's distances away from its prediction is
   never taken for a body fitted at its prediction.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from services.estimation.bodies import label_kernel
from services.estimation.bodies.correspondence import (
    CorrespondenceOptions,
    Views,
    gated_assignment,
    rig_geometry,
    triangulate_blobs,
)
from services.estimation.bodies.rigid import Matching, MatchOptions, fit_labelled, with_the_rest
from services.estimation.bodies.tracking import TrackingOptions, match_with_prediction
from services.geometry.camera import CameraModel
from services.geometry.camera_stack import CameraStack
from services.geometry.se3 import transform_points
from services.geometry.triangulation import TriangulatedPoint

__all__ = ["Found", "label_blobs", "label_parts", "track_blobs", "triangulate_labelled"]

PointArrays = Callable[[list[TriangulatedPoint]], tuple[np.ndarray, np.ndarray]]
"""One instant's points -> their (M, 3) world positions and (M, 3, 3) covariances (m^2)."""


@dataclass(frozen=True)
class Found:
    """One instant: ``points`` (each with the camera and blob indices it was made from), their ``points_world``
    (M, 3) and ``covariances`` (M, 3, 3) m^2, and the bodies found among them (``matching``)."""

    points: list[TriangulatedPoint]
    points_world: np.ndarray
    covariances: np.ndarray
    matching: Matching


def label_blobs(stack: CameraStack, blobs: Sequence[np.ndarray], expected: np.ndarray, gate_px: float
                ) -> tuple[np.ndarray, np.ndarray]:
    """``(labels, projected)``: (S, C) int64, for each predicted sphere (row of (S, 3) ``expected``, world) and
    camera of ``stack``, the index of the blob it labels in ``blobs[c]``, -1 for none (see the module docstring;
    the gating is ``label_kernel.label``'s, the crowded cameras' assignment ``gated_assignment``); and the
    spheres' images (S, C, 2) px, NaN behind a camera (``CameraStack.project``'s)."""
    widest = max(len(b) for b in blobs)
    if not widest:
        return np.full((len(expected), len(stack)), -1, np.int64), stack.project(expected)
    observed = np.zeros((len(stack), widest, 2))
    for c, b in enumerate(blobs):
        observed[c, :len(b)] = b
    counts = np.array([len(b) for b in blobs], np.int64)
    spheres = np.ascontiguousarray(expected, np.float64)
    labels, crowded, near, cost, projected = label_kernel.label(
        stack.K, stack.dist, stack.R_camera_world, stack.t_camera_world, spheres, observed, counts, float(gate_px))
    for c in np.flatnonzero(crowded).tolist():
        for row, column in gated_assignment(np.where(near[:, c], cost[:, c], np.inf), gate_px):
            labels[row, c] = column
    return labels, projected


def label_parts(projected: np.ndarray, blobs: Sequence[np.ndarray], parts: Sequence[np.ndarray], labels: np.ndarray,
                gate_px: float) -> tuple[np.ndarray, list[np.ndarray]]:
    """``(labels, observed)``: ``labels`` (S, C) int64 with the split blobs' parts given to the predicted spheres
    inside them (see the module docstring), and per camera the (N_c + 2 P_c, 2) pixels the labels index: the
    blobs, then the parts in pair order.

    ``projected``: (S, C, 2) the predicted spheres' images (NaN where not seen); ``blobs[c]``: (N_c, 2) clean
    blobs of camera c; ``parts[c]``: (P_c, 2, 2) the two parts of each of its split blobs; ``labels``: (S, C)
    ``label_blobs``' labels, not changed."""
    labels = labels.copy()
    observed = []
    for c, (clean, pairs) in enumerate(zip(blobs, parts, strict=True)):
        observed.append(np.concatenate([clean, pairs.reshape(-1, 2)]))
        if not len(pairs):
            continue
        with np.errstate(invalid="ignore"):
            distance = np.linalg.norm(projected[:, c, None, None, :] - pairs[None], axis=3)
            inside = np.min(distance, axis=2) < gate_px
        for k in range(len(pairs)):
            spheres = np.flatnonzero(inside[:, k])
            if len(spheres) != 2 or np.any(labels[spheres, c] >= 0):
                continue
            near = distance[spheres, k]
            swap = near[0, 1] + near[1, 0] < near[0, 0] + near[1, 1]
            order = [1, 0] if swap else [0, 1]
            if np.all(near[[0, 1], order] < gate_px):
                labels[spheres, c] = len(clean) + 2 * k + np.array(order)
    return labels, observed


def triangulate_labelled(instant: Views, labels: np.ndarray, expected: np.ndarray, options: CorrespondenceOptions
                         ) -> tuple[np.ndarray, list[TriangulatedPoint]]:
    """``(spheres (K,) int64, points)``: the spheres (rows of (S, C) ``labels``) triangulated from the blobs they
    label, each started from its predicted position (row of (S, 3) ``expected``, world), and their points (see
    the module docstring)."""
    rows = np.flatnonzero(np.count_nonzero(labels >= 0, axis=1) >= 2)
    clusters = [[(c, i) for c, i in enumerate(row) if i >= 0] for row in labels[rows].tolist()]
    gate = options.reprojection_gate_px
    solved = instant.drop_worst(clusters, instant.solve(clusters, expected[rows]), gate)
    kept = [k for k, point in enumerate(solved) if point.rms_px <= gate and point.views >= options.min_views]
    return rows[kept], [solved[k] for k in kept]


def track_blobs(cameras: Sequence[CameraModel], blobs: Sequence[np.ndarray], bodies: Mapping[str, np.ndarray],
                predictions: Mapping[str, np.ndarray], arrays: PointArrays,
                correspondence: CorrespondenceOptions, match: MatchOptions, tracking: TrackingOptions,
                parts: Sequence[np.ndarray] | None = None) -> Found:
    """The points of one instant and the bodies among them (see the module docstring).

    ``cameras``: N >= 2 calibrated cameras; ``blobs[c]``: (N_c, 2) observed pixels of camera c; ``bodies``: name
    -> (N, 3) float64 sphere centres, body frame; ``predictions``: name -> (4, 4) predicted ``T_world_body``
    (bodies absent have none); ``arrays``: the points' positions and covariances (the node's centroid noise);
    ``parts[c]``: (P_c, 2, 2) the two parts of each split blob of camera c (none without), each view of a point
    indexing camera c's blobs then its parts. The points are the labelled ones first, then the full path's.
    """
    blobs = [np.asarray(b, dtype=np.float64).reshape(-1, 2) for b in blobs]
    pairs = [np.asarray(p, np.float64).reshape(-1, 2, 2) for p in parts] if parts is not None else []
    split = any(len(p) for p in pairs)
    observed = [np.concatenate([b, p.reshape(-1, 2)]) for b, p in zip(blobs, pairs, strict=True)] if split else blobs
    predicted = [name for name in bodies if name in predictions]
    labelled: list[TriangulatedPoint] = []
    labels: dict[str, np.ndarray] = {}
    if predicted:
        stack = rig_geometry(cameras).stack
        spheres = [np.asarray(bodies[name], np.float64) for name in predicted]
        expected = np.concatenate([transform_points(predictions[name], s) for name, s in zip(predicted, spheres,
                                                                                              strict=True)])
        on_blobs, projected = label_blobs(stack, blobs, expected, tracking.gate_px)
        if split:
            on_blobs, _ = label_parts(projected, blobs, pairs, on_blobs, tracking.gate_px)
        rows, labelled = triangulate_labelled(Views(stack, observed, None, correspondence.covariance_sigma_px),
                                              on_blobs, expected, correspondence)
        point_of_sphere = np.full(len(expected), -1, np.int64)
        point_of_sphere[rows] = np.arange(len(rows))
        first = np.cumsum([0] + [len(s) for s in spheres])
        labels = {name: point_of_sphere[first[k]:first[k + 1]] for k, name in enumerate(predicted)}
    rest = _full_path(cameras, observed, labelled, correspondence)
    found = labelled + rest
    points, covariances = arrays(found)
    fitted = fit_labelled(bodies, points, covariances, labels, match, tracking.min_spheres)
    matching = with_the_rest(list(bodies), fitted, len(found), lambda rest, free: match_with_prediction(
        {name: bodies[name] for name in rest}, points[free],
        {name: predictions[name] for name in rest if name in predictions}, covariances[free], match, tracking))
    return Found(found, points, covariances, matching)


def _full_path(cameras: Sequence[CameraModel], blobs: list[np.ndarray], labelled: list[TriangulatedPoint],
               options: CorrespondenceOptions) -> list[TriangulatedPoint]:
    """``triangulate_blobs`` on the blobs in none of the ``labelled`` points, their indices those of ``blobs``."""
    free = [np.ones(len(b), bool) for b in blobs]
    for point in labelled:
        for c, i in zip(point.camera_indices, point.blob_indices, strict=True):
            free[c][i] = False
    left = [np.flatnonzero(mask) for mask in free]
    if sum(len(indices) > 0 for indices in left) < 2:
        return []
    found = triangulate_blobs(cameras, [b[indices] for b, indices in zip(blobs, left, strict=True)], options)
    return [dataclasses.replace(p, blob_indices=tuple(int(left[c][i]) for c, i in zip(p.camera_indices,
                                                                                      p.blob_indices, strict=True)))
            for p in found]
