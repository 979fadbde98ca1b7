"""AR overlay: a wireframe cube and the axes of each tracked target, drawn on a camera frame.

Per target (``T_camera_target`` (4, 4), side ``size_m``, ``label``), in the target frame
(ArUco's for markers: origin at the centre, x right, y up, z out of the target towards the
camera):

* a cube standing on the target: its base is the square of side ``size_m`` centred on the
  origin in the plane z = 0, its top the same square at z = +``size_m`` (magenta, BGR
  ``CUBE_COLOR``); for a target given an ``outline`` ``(width_m, height_m)`` (an image target),
  that rectangle centred on the origin in the plane z = 0 instead, in the same colour;
* the axes from the origin, ``size_m`` long: x red, y green, z blue (``cv2.drawFrameAxes``'
  colours), drawn over the cube;
* the label, white on a black outline, just above and right of the origin's image.

Every edge is clipped in 3D to the camera's field of view before it is projected: to
z >= ``NEAR_M`` (nothing behind the camera is drawn) and to the pyramid through the image
border, widened by ``FOV_MARGIN`` of its width and height. The border is undistorted with
the calibration, so the pyramid is the view of the lens as calibrated; without the pyramid
a point far outside the view can wrap back into the image through the distortion
polynomial (k1 = -0.25 puts a point 63 degrees off axis at the image centre). The clipped
edges are sampled every 1/``SAMPLES_PER_EDGE`` of their length (only their ends when there
is no distortion) and projected with ``cv2.projectPoints`` and the distortion, so straight
edges bend as the lens bends them, and drawn anti-aliased with sub-pixel vertices.
``cv2.drawFrameAxes`` draws the same axes unclipped (tests/unit/test_estimation_overlay.py
compares the two).

Drawing costs a copy of the frame and then a fixed amount per target, more with distortion.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import cv2
import numpy as np

from services.geometry.camera import UNDISTORT_CRITERIA
from services.geometry.se3 import transform_points
from services.geometry.shapes import check_shape

CUBE_COLOR = (255, 0, 255)
AXIS_COLORS = ((0, 0, 255), (0, 255, 0), (255, 0, 0))
"""BGR colours of the x, y and z axes (as cv2.drawFrameAxes)."""
NEAR_M = 1e-4
"""Edges are clipped to z >= NEAR_M, camera frame, metres."""
FOV_MARGIN = 0.05
"""The clipping pyramid is this fraction of its width (height) wider (taller) on each side than the image."""
SAMPLES_PER_EDGE = 16
BORDER_SAMPLES = 32
"""Points per image side undistorted to find the field of view."""
SHIFT = 4
"""Fractional bits of the vertices handed to cv2.polylines (1/16 px)."""
LABEL_OFFSET_PX = 4


class OverlayTarget(NamedTuple):
    """One target to draw: ``T`` (4, 4) ``T_camera_target``, cube side and axis length ``size_m`` (m),
    ``label``; ``outline``: ``(width_m, height_m)`` of a rectangle drawn instead of the cube (None: the cube)."""

    T: np.ndarray
    size_m: float
    label: str = ""
    outline: tuple[float, float] | None = None


def draw_overlay(image: np.ndarray, K: np.ndarray, dist: np.ndarray | None,
                 targets: Sequence[OverlayTarget | tuple[np.ndarray, float, str]], *,
                 thickness: int | None = None) -> np.ndarray:
    """(H, W, 3) uint8 BGR copy of ``image`` with each target's cube (or outline), axes and label drawn on it.

    ``image``: (H, W) or (H, W, 3) uint8 (also (H, W, 4) BGRA and uint16 mono, see ``to_bgr8``);
    never modified. ``K``: (3, 3) intrinsics of the image; ``dist``: OpenCV distortion
    coefficients (None or empty = none). ``targets``: ``OverlayTarget`` or plain tuples
    ``(T_camera_target (4, 4), size_m, label)``; an empty label draws no text. ``thickness``: line
    width in pixels (default: 1 per 240 pixels of the image's smaller side, at least 1).
    What lies behind the camera or outside the view is not drawn (module docstring). Raises
    ValueError for an image, K, pose or size it cannot use.
    """
    canvas = to_bgr8(image)
    height, width = canvas.shape[:2]
    K = check_shape(K, "3,3", "K", np.float64)
    if not np.all(np.isfinite(K)):
        raise ValueError("K must be finite")
    dist = np.zeros(5) if dist is None or np.size(dist) == 0 else np.asarray(dist, dtype=np.float64).ravel()
    thickness = thickness if thickness is not None else max(1, round(min(height, width) / 240))
    bounds = view_bounds(K, dist, width, height)
    for target in targets:
        T, size_m, label, outline = OverlayTarget(*target)
        T = check_shape(T, "4,4", "T_camera_target", np.float64)
        if not np.all(np.isfinite(T)):
            raise ValueError("T_camera_target must be finite")
        if not (np.isfinite(size_m) and size_m > 0):
            raise ValueError(f"size_m must be a positive length in metres, got {size_m!r}")
        shape = cube_edges(size_m) if outline is None else rectangle_edges(*outline)
        segments = np.concatenate([shape, axis_segments(size_m)])
        colors = (CUBE_COLOR,) * len(shape) + AXIS_COLORS
        _draw_segments(canvas, transform_points(T, segments.reshape(-1, 3)).reshape(-1, 2, 3), colors,
                       K, dist, bounds, thickness)
        if label:
            _draw_label(canvas, label, T[:3, 3], K, dist, bounds)
    return canvas


def to_bgr8(image: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 BGR copy of a (H, W) or (H, W, 1) mono, (H, W, 3) BGR or (H, W, 4) BGRA image.

    uint16 images keep their high byte (a 16-bit frame shown as 8-bit); other dtypes raise ValueError.
    """
    image = np.asarray(image)
    if image.dtype == np.uint16:
        image = (image >> 8).astype(np.uint8)
    if image.dtype != np.uint8:
        raise ValueError(f"the overlay draws on uint8 or uint16 images, got {image.dtype}")
    if image.ndim == 2 or (image.ndim == 3 and image.shape[2] == 1):
        return cv2.cvtColor(image.reshape(image.shape[:2]), cv2.COLOR_GRAY2BGR)
    if image.ndim == 3 and image.shape[2] == 3:
        return image.copy()
    if image.ndim == 3 and image.shape[2] == 4:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2BGR)
    raise ValueError(f"the overlay draws on (H, W), (H, W, 3) or (H, W, 4) images, got shape {image.shape}")


def cube_edges(size_m: float) -> np.ndarray:
    """(12, 2, 3) end points of the cube's edges, target frame: base (z = 0) 4, top (z = size_m) 4, sides 4."""
    h = size_m / 2
    base = np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])
    top = base + [0.0, 0.0, size_m]
    ring = [(i, (i + 1) % 4) for i in range(4)]
    return np.array([[base[i], base[j]] for i, j in ring] + [[top[i], top[j]] for i, j in ring]
                    + [[base[i], top[i]] for i in range(4)])


def rectangle_edges(width_m: float, height_m: float) -> np.ndarray:
    """(4, 2, 3) end points of the edges of a ``width_m`` x ``height_m`` rectangle centred on the origin in the
    plane z = 0, target frame (top, right, bottom, left); ValueError unless both sides are positive."""
    if not (np.isfinite(width_m) and np.isfinite(height_m) and width_m > 0 and height_m > 0):
        raise ValueError(f"an outline needs positive sides in metres, got {width_m!r} x {height_m!r}")
    w, h = width_m / 2, height_m / 2
    corners = np.array([[-w, h, 0.0], [w, h, 0.0], [w, -h, 0.0], [-w, -h, 0.0]])
    return np.array([[corners[i], corners[(i + 1) % 4]] for i in range(4)])


def axis_segments(length_m: float) -> np.ndarray:
    """(3, 2, 3) the x, y and z axes from the origin, ``length_m`` long, target frame."""
    return np.stack([np.zeros((3, 3)), np.eye(3) * length_m], axis=1)


def view_bounds(K: np.ndarray, dist: np.ndarray, width: int, height: int) -> np.ndarray:
    """(4,) ``(x_min, x_max, y_min, y_max)`` of the normalised coordinates (x/z, y/z) that can be seen.

    The image border (pixel edges, -0.5 to W - 0.5 and -0.5 to H - 0.5) undistorted, boxed and
    widened by ``FOV_MARGIN`` on each side.
    """
    u = np.linspace(-0.5, width - 0.5, BORDER_SAMPLES + 1)
    v = np.linspace(-0.5, height - 0.5, BORDER_SAMPLES + 1)
    border = np.concatenate([np.stack([u, np.full_like(u, v[0])], 1), np.stack([u, np.full_like(u, v[-1])], 1),
                             np.stack([np.full_like(v, u[0]), v], 1), np.stack([np.full_like(v, u[-1]), v], 1)])
    normalised = cv2.undistortPoints(border.reshape(-1, 1, 2), K, dist, criteria=UNDISTORT_CRITERIA).reshape(-1, 2)
    low, high = normalised.min(axis=0), normalised.max(axis=0)
    margin = FOV_MARGIN * (high - low)
    low, high = low - margin, high + margin
    return np.array([low[0], high[0], low[1], high[1]])


def clip_to_view(segments: np.ndarray, bounds: np.ndarray, near: float = NEAR_M) -> tuple[np.ndarray, np.ndarray]:
    """The parts of (S, 2, 3) camera-frame segments inside the view: z >= ``near`` and
    ``bounds`` (``view_bounds``) on x/z and y/z.

    Returns ``(kept, t)``: (S,) bool, whether anything of the segment is left, and (S, 2) the
    parameters (0 = first end, 1 = second end) of what is left (Liang-Barsky against 5 planes).
    """
    x_min, x_max, y_min, y_max = bounds
    # Each plane as a . p + b >= 0.
    a = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, -x_min], [-1.0, 0.0, x_max], [0.0, 1.0, -y_min], [0.0, -1.0, y_max]])
    b = np.array([-near, 0.0, 0.0, 0.0, 0.0])
    f0 = segments[:, 0] @ a.T + b
    d = segments[:, 1] @ a.T + b - f0
    with np.errstate(divide="ignore", invalid="ignore"):
        crossing = -f0 / d
    low = np.max(np.where(d > 0, crossing, 0.0), axis=1, initial=0.0)
    high = np.min(np.where(d < 0, crossing, 1.0), axis=1, initial=1.0)
    outside = np.any((d == 0) & (f0 < 0), axis=1)
    return (low <= high) & ~outside, np.stack([low, high], axis=1)


def _draw_segments(canvas: np.ndarray, segments: np.ndarray, colors: Sequence[tuple[int, int, int]],
                   K: np.ndarray, dist: np.ndarray, bounds: np.ndarray, thickness: int) -> None:
    """Draw (S, 2, 3) camera-frame segments, segment i in ``colors[i]``, clipped and distorted.

    Segments are drawn in runs of one colour, each run over the ones before it.
    """
    kept, t = clip_to_view(segments, bounds)
    if not kept.any():
        return
    segments, t, colors = segments[kept], t[kept], [c for c, k in zip(colors, kept, strict=True) if k]
    steps = np.linspace(0.0, 1.0, SAMPLES_PER_EDGE + 1 if np.any(dist) else 2)  # no distortion: straight
    s = t[:, :1] + (t[:, 1:] - t[:, :1]) * steps  # (S, N + 1)
    points = segments[:, :1] + s[..., None] * (segments[:, 1:] - segments[:, :1])  # (S, N + 1, 3)
    pixels, _ = cv2.projectPoints(points.reshape(-1, 3), np.zeros(3), np.zeros(3), K, dist)
    fixed = np.round(np.clip(pixels.reshape(len(points), -1, 2), -1e6, 1e6) * (1 << SHIFT)).astype(np.int32)
    start = 0
    for end in range(1, len(colors) + 1):
        if end == len(colors) or colors[end] != colors[start]:
            cv2.polylines(canvas, list(fixed[start:end]), False, colors[start], thickness, cv2.LINE_AA, SHIFT)
            start = end


def _draw_label(canvas: np.ndarray, label: str, origin_cam: np.ndarray, K: np.ndarray, dist: np.ndarray,
                bounds: np.ndarray) -> None:
    """``label`` just above and right of the origin's pixel, when the origin is in view."""
    kept, _ = clip_to_view(np.stack([origin_cam, origin_cam])[None], bounds)
    if not kept[0]:
        return
    pixel, _ = cv2.projectPoints(origin_cam.reshape(1, 3), np.zeros(3), np.zeros(3), K, dist)
    u, v = np.round(pixel.ravel()).astype(int)
    at = (int(u) + LABEL_OFFSET_PX, int(v) - LABEL_OFFSET_PX)
    scale = max(0.4, min(canvas.shape[:2]) / 960)
    weight = max(1, round(scale * 2))
    cv2.putText(canvas, label, at, cv2.FONT_HERSHEY_SIMPLEX, scale, (0, 0, 0), weight + 2, cv2.LINE_AA)
    cv2.putText(canvas, label, at, cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255), weight, cv2.LINE_AA)


def board_cube_size(corners_target: np.ndarray, marker_length: float) -> float:
    """The cube side for a board: half the smaller side of its markers' bounding box in its x-y plane,
    at least ``marker_length`` (metres).

    ``corners_target``: (N, 3) every marker corner in the board frame. Half the board's smaller
    side is the axis length OpenCV's board samples draw; the floor keeps a one-row board's cube
    as large as one of its markers.
    """
    corners = np.asarray(corners_target, dtype=np.float64).reshape(-1, 3)
    if len(corners) == 0:
        return float(marker_length)
    extent = corners[:, :2].max(axis=0) - corners[:, :2].min(axis=0)
    return float(max(marker_length, 0.5 * extent.min()))
