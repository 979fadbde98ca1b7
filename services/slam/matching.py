"""Matching ORB descriptors between frames and map points, as ORB-SLAM does.

Descriptors are (N, 32) uint8 rows of 256 packed bits, compared by Hamming distance (bits that
differ, 0..256). Pixels are undistorted px (``features``); ``levels`` are pyramid levels.

* ``match_descriptors``: every descriptor of one set against every one of another (brute force,
  OpenCV's ``BFMatcher``), kept when its best distance is small enough and clearly better than its
  second best (Lowe's ratio test) and no other row claims the same column.
* ``match_candidates``: the same two tests over given candidate pairs only (an epipolar band,
  a window around a prediction).
* ``search_by_projection``: map points already projected into a frame, each compared only with
  the frame's keypoints within a window around its predicted pixel (a radius growing with the
  predicted pyramid level) and on a neighbouring level; the same two tests. The keypoints in each
  window come from a grid of square cells (``pairs_within``), listed by array operations with no
  loop over points; in wide windows one predicted level at a time among the keypoints of the
  neighbouring levels only (listing every window's keypoints and dropping the other levels'
  afterwards listed 2.4 times as many pairs in the initialisation's 100 px windows). The matches do
  not depend on the order the candidates are listed in (``match_candidates``).
* ``rotation_consistent``: the matches whose keypoint orientations turned by about the same angle
  as most others (a histogram of 30 bins, its three fullest kept): a cheap check that rejects
  matches no rigid image motion explains.
"""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["hamming", "hamming_matrix", "match_descriptors", "match_candidates", "pairs_within",
           "search_by_projection", "rotation_consistent", "best_two"]

ROTATION_BINS = 30
LEVEL_SPLIT_KEYPOINTS = 30.0
"""``search_by_projection`` lists the candidates one predicted level at a time when its windows hold more
keypoints than this on average (the initialisation's 100 px windows, about 150 of 1500 keypoints at
640x480): fewer pairs listed then outweigh one listing per level; with the tracking searches' small
windows (under 10) one listing costs less."""
MIN_CELL_PX = 8.0
"""The grid of ``pairs_within`` has cells at least this wide (narrower ones would only make more empty cells)."""


def hamming(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(N,) int Hamming distances between rows ``a[i]`` and ``b[i]``, both (N, 32) uint8."""
    if len(a) == 0:
        return np.zeros(0, np.int32)
    words = np.bitwise_xor(np.ascontiguousarray(a).view(np.uint64), np.ascontiguousarray(b).view(np.uint64))
    return np.bitwise_count(words).sum(axis=1, dtype=np.int32)


def hamming_matrix(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(Na, Nb) int Hamming distances between every row of (Na, 32) ``a`` and every row of (Nb, 32) ``b``."""
    words_a, words_b = np.ascontiguousarray(a).view(np.uint64), np.ascontiguousarray(b).view(np.uint64)
    return np.bitwise_count(np.bitwise_xor(words_a[:, None], words_b[None])).sum(axis=2, dtype=np.int32)


def best_two(groups: np.ndarray, costs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For pairs given as (P,) ``groups`` and (P,) ``costs``: ``(rows, best, second)`` where ``rows``
    indexes each group's cheapest pair, ``best`` its cost and ``second`` the group's second cheapest
    cost (inf when the group has one pair); among equal costs the earlier pair. Non-negative integer costs
    of non-negative groups are sorted on one key (group and cost in one integer), others by ``lexsort``."""
    if len(groups) == 0:
        return np.zeros(0, np.int64), np.zeros(0), np.zeros(0)
    if np.issubdtype(costs.dtype, np.integer) and costs.min() >= 0 and groups.min() >= 0:
        order = np.argsort(groups.astype(np.int64) * (int(costs.max()) + 1) + costs, kind="stable")
    else:
        order = np.lexsort((costs, groups))
    g = groups[order]
    first = np.flatnonzero(np.r_[True, g[1:] != g[:-1]])
    has_second = (first + 1 < len(g)) & (g[np.minimum(first + 1, len(g) - 1)] == g[first])
    second = np.where(has_second, costs[order][np.minimum(first + 1, len(g) - 1)], np.inf)
    return order[first], costs[order][first].astype(np.float64), second.astype(np.float64)


def _unique_columns(rows: np.ndarray, columns: np.ndarray, costs: np.ndarray) -> np.ndarray:
    """Indices into the (M,) matches keeping, for every column, only its cheapest row."""
    keep, _, _ = best_two(columns, costs)
    return np.sort(keep)


def match_descriptors(a: np.ndarray, b: np.ndarray, max_distance: int, ratio: float) -> tuple[np.ndarray, np.ndarray]:
    """``(rows of a, rows of b)`` (M,) int64 each: descriptor matches between (Na, 32) ``a`` and
    (Nb, 32) ``b`` whose distance is at most ``max_distance`` and below ``ratio`` times the row's
    second best; one match per row of b (the closest)."""
    if len(a) == 0 or len(b) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    pairs = cv2.BFMatcher(cv2.NORM_HAMMING).knnMatch(a, b, k=2)
    found = np.array([(m[0].queryIdx, m[0].trainIdx, m[0].distance, m[1].distance if len(m) == 2 else np.inf)
                      for m in pairs if len(m)], np.float64).reshape(-1, 4)
    good = (found[:, 2] <= max_distance) & (found[:, 2] < ratio * found[:, 3])
    found = found[good]
    kept = _unique_columns(found[:, 0].astype(np.int64), found[:, 1].astype(np.int64), found[:, 2])
    return found[kept, 0].astype(np.int64), found[kept, 1].astype(np.int64)


def match_candidates(a: np.ndarray, b: np.ndarray, rows: np.ndarray, columns: np.ndarray, max_distance: int,
                     ratio: float) -> tuple[np.ndarray, np.ndarray]:
    """``(rows of a, rows of b)`` (M,) int64: descriptor matches between (Na, 32) ``a`` and (Nb, 32)
    ``b`` among the (P,) candidate pairs ``(a[rows], b[columns])`` only; each row's best candidate is
    kept when at most ``max_distance`` and under ``ratio`` times the row's second best candidate, and a
    column claimed by several rows goes to the closest (the lowest row among equals), whatever order
    the candidates come in; the matches are in increasing row order."""
    if len(rows) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    distances = hamming(a[rows], b[columns])
    best, best_distance, second = best_two(rows, distances)
    best = best[(best_distance <= max_distance) & (best_distance < ratio * second)]
    kept = best[_unique_columns(rows[best], columns[best], distances[best])]
    return rows[kept], columns[kept]


def pairs_within(centres: np.ndarray, radii: np.ndarray, pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(rows, columns)`` (M,) int64, in no particular order: every pair whose ``pixels[column]``
    ((N, 2) px) lies within ``radii[row]`` ((P,) px, distance <= radius) of ``centres[row]`` ((P, 2) px).

    The pixels are sorted into square cells a quarter of the largest radius wide (at least ``MIN_CELL_PX``),
    row by row, so that the cells a window's square overlaps in one row of the grid hold one slice of the
    sorted pixels; the slices of every window, one grid row at a time, are listed at once and their pixels
    kept by their squared distance. A centre or radius that is not finite has no pairs."""
    empty = np.zeros(0, np.int64)
    centres, pixels = np.asarray(centres, np.float64), np.asarray(pixels, np.float64)
    radii = np.asarray(radii, np.float64)
    finite = np.flatnonzero(np.isfinite(centres).all(axis=1) & np.isfinite(radii) & (radii >= 0))
    if len(finite) == 0 or len(pixels) == 0:
        return empty, empty
    cell = max(float(radii[finite].max()) / 4, MIN_CELL_PX)
    origin = pixels.min(axis=0)
    cells = np.floor((pixels - origin) / cell).astype(np.int64)
    size = cells.max(axis=0) + 1
    width = int(size[0])
    ids = cells[:, 1] * width + cells[:, 0]
    order = np.argsort(ids, kind="stable")
    bounds = np.searchsorted(ids[order], np.arange(width * int(size[1]) + 1))
    reach = radii[finite, None]
    low = np.floor((centres[finite] - reach - origin) / cell).astype(np.int64)
    high = np.floor((centres[finite] + reach - origin) / cell).astype(np.int64)
    seen = np.all((high >= 0) & (low < size), axis=1)
    finite, low, high = finite[seen], np.maximum(low[seen], 0), np.minimum(high[seen], size - 1)
    rows, starts, counts = [], [], []
    for step in range(int((high[:, 1] - low[:, 1]).max(initial=-1)) + 1):
        y = low[:, 1] + step
        within = np.flatnonzero(y <= high[:, 1])
        first = bounds[y[within] * width + low[within, 0]]
        rows.append(finite[within])
        starts.append(first)
        counts.append(bounds[y[within] * width + high[within, 0] + 1] - first)
    if not rows:
        return empty, empty
    row_of, start, count = np.concatenate(rows), np.concatenate(starts), np.concatenate(counts)
    total = int(count.sum())
    if total == 0:
        return empty, empty
    columns = order[np.arange(total) + np.repeat(start - (np.cumsum(count) - count), count)]
    row_of = np.repeat(row_of, count)
    offsets = pixels[columns] - centres[row_of]
    near = offsets[:, 0] * offsets[:, 0] + offsets[:, 1] * offsets[:, 1] <= radii[row_of] * radii[row_of]
    return row_of[near], columns[near]


def search_by_projection(predicted: np.ndarray, radii: np.ndarray, levels: np.ndarray, descriptors: np.ndarray,
                         frame_pixels: np.ndarray, frame_levels: np.ndarray, frame_descriptors: np.ndarray,
                         available: np.ndarray, max_distance: int, ratio: float,
                         level_slack: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """``(point rows, keypoint indices)`` (M,) int64: each of P projected points matched to at most
    one free keypoint of the frame.

    ``predicted`` (P, 2) px, ``radii`` (P,) px search windows, ``levels`` (P,) predicted pyramid
    levels, ``descriptors`` (P, 32); the frame's N keypoints ``frame_pixels`` (N, 2),
    ``frame_levels`` (N,), ``frame_descriptors`` (N, 32), ``available`` (N,) bool (keypoints already
    matched are False). A candidate lies within the point's radius and within ``level_slack``
    levels of its predicted level; the best is kept when at most ``max_distance`` and under
    ``ratio`` times the second best; a keypoint claimed by several points goes to the closest."""
    free = np.flatnonzero(available)
    if len(predicted) == 0 or len(free) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    if _keypoints_per_window(radii, frame_pixels[free]) < LEVEL_SPLIT_KEYPOINTS:
        rows, columns = pairs_within(predicted, radii, frame_pixels[free])
        columns = free[columns]
        near_level = np.abs(frame_levels[columns] - levels[rows]) <= level_slack
        return match_candidates(descriptors, frame_descriptors, rows[near_level], columns[near_level], max_distance,
                                ratio)
    row_parts, column_parts = [], []
    for level in np.unique(levels):
        points = np.flatnonzero(levels == level)
        near = free[np.abs(frame_levels[free] - level) <= level_slack]
        found, keypoints = pairs_within(predicted[points], radii[points], frame_pixels[near])
        row_parts.append(points[found])
        column_parts.append(near[keypoints])
    return match_candidates(descriptors, frame_descriptors, np.concatenate(row_parts), np.concatenate(column_parts),
                            max_distance, ratio)


def _keypoints_per_window(radii: np.ndarray, pixels: np.ndarray) -> float:
    """About how many of the (N, 2) ``pixels`` a window of the (P,) ``radii`` holds on average, were they
    spread evenly over their bounding box."""
    finite = radii[np.isfinite(radii)]
    area = float(np.prod(np.ptp(pixels, axis=0))) if len(pixels) > 1 else 0.0
    if len(finite) == 0 or area <= 0:
        return 0.0
    return float(np.pi * np.mean(finite**2) * len(pixels) / area)


def rotation_consistent(angles_a: np.ndarray, angles_b: np.ndarray) -> np.ndarray:
    """(M,) bool: the matches whose orientation change ``angles_b - angles_a`` (degrees, (M,) each)
    falls in one of the three fullest of ``ROTATION_BINS`` bins (a bin under a tenth of the fullest
    is not kept)."""
    if len(angles_a) == 0:
        return np.zeros(0, bool)
    turn = np.mod(np.asarray(angles_b, np.float64) - np.asarray(angles_a, np.float64), 360.0)
    bins = np.minimum((turn * ROTATION_BINS / 360.0).astype(np.int64), ROTATION_BINS - 1)
    counts = np.bincount(bins, minlength=ROTATION_BINS)
    top = np.argsort(-counts, kind="stable")[:3]
    top = top[counts[top] >= 0.1 * counts[top[0]]]
    return np.isin(bins, top)
