"""Compiled labelling of one instant's blobs by the predicted spheres: ``labelled.label_blobs``' gating in
machine code (``numba``), without Python's lock.

Every predicted sphere (world) is projected into every camera through its plumb_bob distortion
(``triangulation_kernel.project_point``; no image behind the camera), and each blob of that camera within
``gate`` px of it is near it. A blob near two spheres or more is doubtful: it is near none, and neither is
any sphere it was near, in that camera. A camera where a sphere is still near two blobs is crowded, and left
to the caller's assignment; in the others each sphere near one blob labels it (no blob is then near two).
For the few spheres and blobs of a motion-capture instant the NumPy version costs more in calls than in
arithmetic. Cached on disk beside this module (``cache=True``).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from services.geometry.triangulation_kernel import project_point

__all__ = ["label", "warm"]


@njit(cache=True, nogil=True)
def label(K: np.ndarray, dist: np.ndarray, R: np.ndarray, t: np.ndarray, expected: np.ndarray, observed: np.ndarray,
          counts: np.ndarray, gate: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(labels (S, C) int64, crowded (C,) bool, near (S, C, W) bool, cost (S, C, W) px, projected (S, C, 2) px)``.

    Cameras: ``K`` (C, 3, 3), ``dist`` (C, 5), ``R`` (C, 3, 3) and ``t`` (C, 3) world into camera;
    ``expected``: (S, 3) predicted sphere centres, world, m; ``observed``: (C, W, 2) each camera's blobs (px),
    the first ``counts[c]`` of row c. ``labels[s, c]``: the blob sphere s labels in camera c, -1 for none or
    where ``crowded[c]``; ``near`` and ``cost`` (inf where not computed) for a crowded camera's assignment;
    ``projected``: NaN where the sphere is behind the camera."""
    spheres, cameras, widest = expected.shape[0], K.shape[0], observed.shape[1]
    projected = np.full((spheres, cameras, 2), np.nan)
    cost = np.full((spheres, cameras, widest), np.inf)
    near = np.zeros((spheres, cameras, widest), np.bool_)
    pixel = np.empty(2)
    jacobian = np.empty((2, 3))
    for s in range(spheres):
        X = expected[s]
        for c in range(cameras):
            if not R[c, 2, 0] * X[0] + R[c, 2, 1] * X[1] + R[c, 2, 2] * X[2] + t[c, 2] > 0.0:
                continue
            project_point(K, dist, R, t, c, X, pixel, jacobian)
            projected[s, c, 0], projected[s, c, 1] = pixel[0], pixel[1]
            for j in range(counts[c]):
                distance = np.sqrt((pixel[0] - observed[c, j, 0]) ** 2 + (pixel[1] - observed[c, j, 1]) ** 2)
                cost[s, c, j] = distance
                near[s, c, j] = distance < gate
    doubtful = np.zeros((cameras, widest), np.bool_)
    for c in range(cameras):
        for j in range(counts[c]):
            doubtful[c, j] = np.count_nonzero(near[:, c, j]) >= 2
    for s in range(spheres):
        for c in range(cameras):
            if np.any(near[s, c] & doubtful[c]):
                near[s, c, :] = False
    for c in range(cameras):
        for j in range(counts[c]):
            if doubtful[c, j]:
                near[:, c, j] = False
    labels = np.full((spheres, cameras), -1, np.int64)
    crowded = np.zeros(cameras, np.bool_)
    for c in range(cameras):
        for s in range(spheres):
            if np.count_nonzero(near[s, c]) > 1:
                crowded[c] = True
        if crowded[c]:
            continue
        for s in range(spheres):
            for j in range(counts[c]):
                if near[s, c, j]:
                    labels[s, c] = j
    return labels, crowded, near, cost, projected


def warm() -> None:
    """Compile ``label`` (or load it from the disk cache) on one sphere seen by two cameras."""
    K = np.array([[[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]]] * 2)
    R = np.array([np.eye(3)] * 2)
    t = np.array([[0.0, 0.0, 0.0], [-0.1, 0.0, 0.0]])
    label(K, np.zeros((2, 5)), R, t, np.array([[0.0, 0.0, 2.0]]), np.array([[[320.0, 240.0]], [[295.0, 240.0]]]),
          np.array([1, 1], np.int64), 3.0)
