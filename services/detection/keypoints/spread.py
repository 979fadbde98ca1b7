"""Spreading keypoints over an image: grid bucketing and adaptive non-maximal suppression (ANMS).

A detector left alone puts most of its strongest points where the texture is richest; a pose
from points bunched in one corner of the image is poorly conditioned. Both functions pick at
most ``count`` of N candidates and return their indices, strongest first.

* ``spread_grid``: the image is cut into square cells of ``cell_px``; every cell keeps its
  strongest points up to one share ``q``, the smallest share that fills ``count`` (cells with
  little texture leave their unused places to the others, and none keeps more than ``q``).
* ``spread_anms``: Brown, Szeliski and Winder's ANMS (2005). A point's suppression radius is
  the distance to the nearest point clearly stronger than it (``response < robustness *
  their response``); the strongest point's radius is infinite. The ``count`` points of largest
  radius are kept: strong points that are also far from stronger ones.

Points are (N, 2) px, x right, y down; responses (N,), larger is stronger.
"""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["cell_share", "grid_cells", "spread_anms", "spread_grid", "suppression_radii"]

ANMS_BLOCK = 64
"""Candidates whose radii are computed at once."""


def grid_cells(points: np.ndarray, shape: tuple[int, int], cell_px: float) -> np.ndarray:
    """(N,) int64: the grid cell of each point, row-major over cells of ``cell_px`` in an image of ``shape`` (H, W)."""
    columns = max(int(np.ceil(shape[1] / cell_px)), 1)
    rows = max(int(np.ceil(shape[0] / cell_px)), 1)
    column = np.clip(np.floor(points[:, 0] / cell_px), 0, columns - 1).astype(np.int64)
    row = np.clip(np.floor(points[:, 1] / cell_px), 0, rows - 1).astype(np.int64)
    return row * columns + column


def cell_share(per_cell: np.ndarray, count: int) -> int:
    """The smallest ``q`` with ``sum(min(per_cell, q)) >= count``, or the largest cell's count when none fills it."""
    if count <= 0 or len(per_cell) == 0:
        return 0
    share = max(-(-count // len(per_cell)), 1)
    while share < per_cell.max() and np.minimum(per_cell, share).sum() < count:
        share += 1
    return int(min(share, per_cell.max()))


def spread_grid(points: np.ndarray, responses: np.ndarray, shape: tuple[int, int], count: int,
                cell_px: float) -> np.ndarray:
    """(M,) int64 indices, M <= ``count``, of the candidates kept by grid bucketing, strongest first."""
    if len(points) == 0 or count <= 0:
        return np.zeros(0, np.int64)
    cells = grid_cells(points, shape, cell_px)
    order = np.lexsort((-responses, cells))
    sorted_cells = cells[order]
    first = np.searchsorted(sorted_cells, sorted_cells, side="left")
    rank = np.arange(len(order)) - first
    share = cell_share(np.bincount(cells), count)
    kept = order[rank < share]
    return kept[np.argsort(-responses[kept], kind="stable")][:count]


def suppression_radii(points: np.ndarray, responses: np.ndarray, robustness: float = 0.9) -> np.ndarray:
    """(N,) float64: each candidate's distance to the nearest candidate with ``response > its response / robustness``
    (infinite for those with none)."""
    n = len(points)
    order = np.argsort(-responses, kind="stable")
    xy = np.ascontiguousarray(points[order], np.float32)
    strength = responses[order].astype(np.float64)
    # candidates before position stronger[i] in the sorted order are the ones that suppress candidate i
    stronger = np.searchsorted(-strength * robustness, -strength, side="left")
    nearest = np.full(n, np.inf)
    for start in range(0, n, ANMS_BLOCK):
        stop = min(start + ANMS_BLOCK, n)
        common, reach = int(stronger[start:stop].min()), int(stronger[start:stop].max())
        if common:  # suppressors of every candidate of the block: nearest neighbour by OpenCV
            squared, _ = cv2.batchDistance(xy[start:stop], xy[:common], cv2.CV_32F, normType=cv2.NORM_L2SQR, K=1)
            nearest[start:stop] = squared[:, 0]
        if reach > common:  # suppressors of some of them only
            strip = ((xy[start:stop, None, :] - xy[None, common:reach, :]) ** 2).sum(axis=2)
            suppressors = np.arange(common, reach)[None, :] < stronger[start:stop, None]
            nearest[start:stop] = np.minimum(nearest[start:stop], np.where(suppressors, strip, np.inf).min(axis=1))
    radii = np.empty(n)
    radii[order] = np.sqrt(nearest)
    return radii


def spread_anms(points: np.ndarray, responses: np.ndarray, count: int, robustness: float = 0.9) -> np.ndarray:
    """(M,) int64 indices, M <= ``count``, of the candidates of largest suppression radius, strongest first."""
    if len(points) == 0 or count <= 0:
        return np.zeros(0, np.int64)
    radii = suppression_radii(points, responses, robustness)
    kept = np.lexsort((-responses, -radii))[:count]
    return kept[np.argsort(-responses[kept], kind="stable")]
