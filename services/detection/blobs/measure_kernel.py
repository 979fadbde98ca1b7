"""Compiled measurements of bright components: the per-component loop of ``bright.detect_ir_blobs`` in machine
code (``numba``), run without Python's global lock.

Given an image, its thresholded binary image and the components' external borders (``cv2.findContours``,
``RETR_EXTERNAL``, ``CHAIN_APPROX_NONE``: 8-connected chains of pixel centres), ``measure`` gives, per
component, in one call:

* its window: the bounding box grown by ``pad`` pixels within the image;
* its filled pixels (the component and its holes, as ``cv2.drawContours(..., cv2.FILLED)`` draws the border):
  every window pixel that a 4-connected walk from the window's edge cannot reach without crossing the border
  (an 8-connected closed chain stops such a walk), the count of them its area;
* its centroid weights, ``max(level - background, 0)`` over the filled pixels and their 8-neighbours that are
  not bright (``binary`` 0), 0 elsewhere, written to a buffer shared by all windows (float32);
* the raw moments of those weights up to the second order, and the central ones (``cv2.moments``'s);
* the border's length as a closed polygon (``cv2.arcLength``), the polygon's area (``cv2.contourArea``) and
  its convex hull's area (``cv2.convexHull``, by the monotone chain).

A blob detector runs on one camera's frames in its own thread; without the lock held here, the detectors of a
rig's cameras measure in parallel on the cores rather than one at a time. Cached on disk beside this module
(``cache=True``).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from services.detection.blobs.merged_kernel import has_waist, split

__all__ = ["CLIPPED", "COLUMNS", "MERGED", "OCCLUDED", "SPLIT", "blob_rows", "measure", "moment_shape", "warm"]

MERGED, OCCLUDED, CLIPPED, SPLIT = 1, 2, 4, 8
"""The bits of ``bright.BlobFlag``."""

COLUMNS = ("x0", "y0", "height", "width", "offset", "area", "perimeter", "polygon_area", "hull_area", "m00", "m10",
           "m01", "mu20", "mu11", "mu02", "box_x", "box_y", "box_w", "box_h")
"""The columns of ``measure``'s table, one row per component: the window's origin and size (px), where its
weights start in the buffer, then the measurements (px, px^2, weight moments in window pixels), then the
border's bounding box ``(x, y, w, h)``."""

_STEPS = ((1, 0), (-1, 0), (0, 1), (0, -1))


@njit(cache=True, nogil=True)
def _filled(wall: np.ndarray) -> np.ndarray:
    """(h, w) bool: the pixels of a window that no 4-connected walk from its edge reaches through pixels off the
    (h, w) bool ``wall``."""
    height, width = wall.shape
    outside = np.zeros((height, width), np.bool_)
    stack = np.empty((height * width, 2), np.int64)
    top = 0
    for y in range(height):
        for x in range(width):
            if (y == 0 or x == 0 or y == height - 1 or x == width - 1) and not wall[y, x] and not outside[y, x]:
                outside[y, x] = True
                stack[top, 0], stack[top, 1] = y, x
                top += 1
    while top > 0:
        top -= 1
        y, x = stack[top, 0], stack[top, 1]
        for dy, dx in _STEPS:
            ny, nx = y + dy, x + dx
            if 0 <= ny < height and 0 <= nx < width and not wall[ny, nx] and not outside[ny, nx]:
                outside[ny, nx] = True
                stack[top, 0], stack[top, 1] = ny, nx
                top += 1
    return ~outside


@njit(cache=True, nogil=True)
def _hull_area(points: np.ndarray) -> float:
    """The area of the convex hull of (n, 2) integer points (Andrew's monotone chain, exact in integers)."""
    order = np.argsort(points[:, 0] * (1 << 32) + points[:, 1])
    n = len(order)
    if n < 3:
        return 0.0
    chain = np.empty((2 * n, 2), np.int64)
    k = 0
    for rounds in range(2):
        start = k
        for index in range(n):
            i = order[index] if rounds == 0 else order[n - 1 - index]
            px, py = points[i, 0], points[i, 1]
            while k >= start + 2 and ((chain[k - 1, 0] - chain[k - 2, 0]) * (py - chain[k - 2, 1])
                                      - (chain[k - 1, 1] - chain[k - 2, 1]) * (px - chain[k - 2, 0])) <= 0:
                k -= 1
            chain[k, 0], chain[k, 1] = px, py
            k += 1
        k -= 1
    twice = 0
    for i in range(k):
        j = (i + 1) % k
        twice += chain[i, 0] * chain[j, 1] - chain[j, 0] * chain[i, 1]
    return abs(twice) / 2.0


@njit(cache=True, nogil=True)
def _touches(filled: np.ndarray, y: int, x: int) -> bool:
    """Whether pixel (``y``, ``x``) of a window has a filled 8-neighbour in (h, w) bool ``filled``."""
    height, width = filled.shape
    for ny in range(max(y - 1, 0), min(y + 2, height)):
        for nx in range(max(x - 1, 0), min(x + 2, width)):
            if filled[ny, nx]:
                return True
    return False


@njit(cache=True, nogil=True)
def measure(image: np.ndarray, binary: np.ndarray, points: np.ndarray, starts: np.ndarray, background: float,
            pad: int) -> tuple[np.ndarray, np.ndarray]:
    """``(table, weights)`` for the components whose borders are ``points[starts[k]:starts[k + 1]]``.

    ``image``: (H, W) uint8 or uint16 levels; ``binary``: (H, W) uint8, non-zero where bright; ``points``: (M, 2)
    int32 border pixels ``(x, y)``; ``starts``: (K + 1,) int64. ``table``: (K, len(COLUMNS)) float64, the
    columns of ``COLUMNS``; ``weights``: float32, window k's (height, width) weights at ``offset``, row-major.
    """
    image_height, image_width = image.shape
    count = len(starts) - 1
    table = np.zeros((count, len(COLUMNS)))
    total = 0
    for k in range(count):
        border = points[starts[k]:starts[k + 1]]
        x_min, y_min = border[:, 0].min(), border[:, 1].min()
        x_max, y_max = border[:, 0].max(), border[:, 1].max()
        x0, y0 = max(x_min - pad, 0), max(y_min - pad, 0)
        x1, y1 = min(x_max + 1 + pad, image_width), min(y_max + 1 + pad, image_height)
        row = table[k]
        row[0], row[1], row[2], row[3], row[4] = x0, y0, y1 - y0, x1 - x0, total
        row[15], row[16], row[17], row[18] = x_min, y_min, x_max - x_min + 1, y_max - y_min + 1
        total += (y1 - y0) * (x1 - x0)
    weights = np.zeros(total, np.float32)
    for k in range(count):
        row = table[k]
        x0, y0, height, width, offset = int(row[0]), int(row[1]), int(row[2]), int(row[3]), int(row[4])
        border = points[starts[k]:starts[k + 1]]
        wall = np.zeros((height, width), np.bool_)
        for i in range(len(border)):
            wall[border[i, 1] - y0, border[i, 0] - x0] = True
        filled = _filled(wall)
        area = 0
        m00 = m10 = m01 = m20 = m11 = m02 = 0.0
        for y in range(height):
            s0 = s1 = s2 = 0.0
            for x in range(width):
                if filled[y, x]:
                    area += 1
                elif binary[y0 + y, x0 + x] != 0 or not _touches(filled, y, x):
                    continue
                weight = np.float32(image[y0 + y, x0 + x]) - np.float32(background)
                if weight > 0.0:
                    weights[offset + y * width + x] = weight
                    p = np.float64(weight)
                    xp = x * p
                    s0 += p
                    s1 += xp
                    s2 += xp * x
            m00 += s0
            m10 += s1
            m20 += s2
            m01 += y * s0
            m11 += s1 * y
            m02 += s0 * (y * y)
        n = len(border)
        perimeter = 0.0
        twice = 0
        for i in range(n):
            j = i - 1 if i > 0 else n - 1
            dx, dy = np.float32(border[i, 0] - border[j, 0]), np.float32(border[i, 1] - border[j, 1])
            perimeter += np.sqrt(dx * dx + dy * dy)
            twice += np.int64(border[j, 0]) * border[i, 1] - np.int64(border[j, 1]) * border[i, 0]
        row[5], row[6], row[7], row[8] = area, perimeter, abs(twice) / 2.0, _hull_area(border.astype(np.int64))
        row[9], row[10], row[11] = m00, m10, m01
        if m00 > 0.0:
            inverse = 1.0 / m00
            cx, cy = m10 * inverse, m01 * inverse
            row[12], row[13], row[14] = m20 - m10 * cx, m11 - m10 * cy, m02 - m01 * cy
    return table, weights


@njit(cache=True, nogil=True)
def moment_shape(m00: float, m10: float, m01: float, mu20: float, mu11: float,
                 mu02: float) -> tuple[float, float, float, float, float]:
    """From the raw and central moments of a weight window (``m00`` > 0): the centroid ``(x, y)`` px in the
    window, the major axis ``(cos, sin)`` (a unit vector) and the roundness ``sqrt(l_min / l_max)`` of the
    covariance, as ``(x, y, cos, sin, roundness)``."""
    a, b, c = mu20 / m00, mu11 / m00, mu02 / m00
    half_gap = math.hypot((a - c) / 2.0, b)
    l_max, l_min = (a + c) / 2.0 + half_gap, max((a + c) / 2.0 - half_gap, 0.0)
    angle = 0.5 * math.atan2(2.0 * b, a - c)
    roundness = math.sqrt(l_min / l_max) if l_max > 0 else 1.0
    return m10 / m00, m01 / m00, math.cos(angle), math.sin(angle), roundness


@njit(cache=True, nogil=True)
def blob_rows(table: np.ndarray, weights: np.ndarray, image_width: int, image_height: int, min_area: float,
              max_area: float, min_radius: float, max_radius: float, min_circularity: float, min_roundness: float,
              min_solidity: float, waist_depth: float) -> np.ndarray:
    """(M, 8) float64 rows ``(x, y, area, radius, perimeter, circularity, quality, flags)`` of the blobs of
    ``measure``'s ``(table, weights)`` in an image of ``image_width`` x ``image_height`` px, in the table's order,
    each split blob followed by its two discs: the filters, shape, flags and splits ``bright.detect_ir_blobs``
    states, with its ``IrBlobParams`` and ``ShapeParams`` settings."""
    rows = np.empty((3 * len(table), 8))
    count = 0
    for k in range(len(table)):
        (x0, y0, height, width, offset, area, perimeter, polygon_area, hull_area, m00, m10, m01, mu20, mu11, mu02,
         box_x, box_y, box_w, box_h) = table[k]
        radius = math.sqrt(area / math.pi)
        if not (box_w * box_h >= min_area and min_area <= area <= max_area and min_radius <= radius <= max_radius):
            continue
        circularity = min(4.0 * math.pi * polygon_area / (perimeter * perimeter), 1.0) if perimeter > 0 else 0.0
        if circularity < min_circularity or m00 <= 0.0:
            continue
        cx, cy, ax, ay, roundness = moment_shape(m00, m10, m01, mu20, mu11, mu02)
        solidity = min(polygon_area / hull_area, 1.0) if hull_area > 0 else 1.0
        start = int(offset)
        window = weights[start:start + int(height) * int(width)].reshape(int(height), int(width))
        flags = 0
        if roundness < min_roundness or solidity < min_solidity:
            flags = MERGED if has_waist(window, cx, cy, ax, ay, waist_depth) else OCCLUDED
        if box_x == 0 or box_y == 0 or box_x + box_w == image_width or box_y + box_h == image_height:
            flags |= CLIPPED
        rows[count] = (x0 + cx, y0 + cy, area, radius, perimeter, circularity, roundness * solidity, float(flags))
        count += 1
        if flags & (MERGED | OCCLUDED) == 0:
            continue
        fitted, params, rms = split(window, cx, cy, ax, ay)
        if fitted:
            for disc in range(2):
                r = params[4 + disc]
                rows[count] = (x0 + params[2 * disc], y0 + params[2 * disc + 1], math.pi * r * r, r,
                               2.0 * math.pi * r, 1.0, 1.0 - rms, float(SPLIT | (flags & CLIPPED)))
                count += 1
    return rows[:count].copy()


def warm() -> None:
    """``measure`` and ``blob_rows`` run once on a tiny input of each image depth, and ``moment_shape`` once:
    compiled, or loaded from the cache."""
    moment_shape(1.0, 0.0, 0.0, 1.0, 0.0, 1.0)
    binary = np.zeros((8, 8), np.uint8)
    binary[3:5, 3:5] = 255
    points = np.array([[3, 3], [3, 4], [4, 4], [4, 3]], np.int32)
    starts = np.array([0, 4], np.int64)
    for depth in (np.uint8, np.uint16):
        table, weights = measure(binary.astype(depth), binary, points, starts, 0.0, 2)
        blob_rows(table, weights, 8, 8, 1.0, 100.0, 0.0, math.inf, 0.3, 0.8, 0.85, 0.05)
