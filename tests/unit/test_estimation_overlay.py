"""The AR overlay: cube and axes drawn where the pose projects them, nothing behind or beyond the view."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from services.estimation.markers.map import grid_map
from services.estimation.overlay import (
    AXIS_COLORS,
    OverlayTarget,
    axis_segments,
    board_cube_size,
    cube_edges,
    draw_overlay,
    rectangle_edges,
    to_bgr8,
)
from services.geometry.rotation import matrix_from_rotvec
from services.geometry.se3 import make_transform, transform_points

W, H = 640, 480
K = np.array([[600.0, 0.0, 319.5], [0.0, 600.0, 239.5], [0.0, 0.0, 1.0]])
GREY = 128
SIZE = 0.08
THICKNESS = 2


def facing(translation, tilt=(0.25, -0.3, 0.1)) -> np.ndarray:
    """T_camera_target of a target at ``translation`` facing the camera (its z towards it), slightly tilted."""
    return make_transform(matrix_from_rotvec(np.array([np.pi, 0.0, 0.0])) @ matrix_from_rotvec(np.array(tilt)),
                          np.asarray(translation, dtype=np.float64))


def project(T: np.ndarray, points_target: np.ndarray, dist=None) -> np.ndarray:
    """(N, 2) pixels of target-frame points."""
    points = transform_points(T, points_target)
    pixels, _ = cv2.projectPoints(points, np.zeros(3), np.zeros(3), K, np.zeros(5) if dist is None else dist)
    return pixels.reshape(-1, 2)


def changed(before: np.ndarray, after: np.ndarray, tolerance: int = 0) -> np.ndarray:
    """(H, W) bool: pixels whose BGR value differs by more than ``tolerance`` in some channel."""
    return np.any(np.abs(to_bgr8(before).astype(int) - after.astype(int)) > tolerance, axis=2)


def grey(shape=(H, W)) -> np.ndarray:
    return np.full(shape, GREY, np.uint8)


def at(mask: np.ndarray, pixel) -> bool:
    u, v = np.round(pixel).astype(int)
    return bool(mask[v, u])


def test_cube_and_axes_are_drawn_where_they_project_and_nowhere_else():
    T = facing([0.03, -0.02, 0.6])
    image = grey()
    out = draw_overlay(image, K, None, [(T, SIZE, "")], thickness=THICKNESS)
    drawn = changed(image, out)

    edges = cube_edges(SIZE)
    corners = project(T, edges[:, 0])
    assert all(at(drawn, p) for p in corners), "a cube corner was not drawn"
    middles = project(T, edges.mean(axis=1))
    assert all(at(drawn, p) for p in middles), "a cube edge was not drawn"
    tips = project(T, axis_segments(SIZE)[:, 1] * 0.9)
    for tip, color in zip(tips, AXIS_COLORS, strict=True):
        u, v = np.round(tip).astype(int)
        assert np.argmax(out[v, u]) == np.argmax(color), (tip, out[v, u])

    # Every visible change lies within a few pixels of a projected edge or axis (anti-aliasing
    # leaves a faint fringe of +-1 grey level a little further out).
    near = np.zeros((H, W), np.uint8)
    for a, b in np.concatenate([edges, axis_segments(SIZE)]):
        p, q = np.round(project(T, np.stack([a, b]))).astype(int)
        cv2.line(near, tuple(map(int, p)), tuple(map(int, q)), 1, THICKNESS + 4)
    assert drawn.sum() > 500
    assert not np.any(changed(image, out, tolerance=4) & (near == 0)), "pixels away from the cube and axes changed"


def test_an_outline_is_drawn_instead_of_the_cube():
    T = facing([0.03, -0.02, 0.6])
    image = grey()
    outline = (0.12, 0.06)
    out = draw_overlay(image, K, None, [OverlayTarget(T, SIZE / 2, "", outline)], thickness=THICKNESS)
    drawn = changed(image, out)
    edges = rectangle_edges(*outline)
    assert all(at(drawn, p) for p in project(T, edges.mean(axis=1))), "an outline edge was not drawn"
    near = np.zeros((H, W), np.uint8)
    for a, b in np.concatenate([edges, axis_segments(SIZE / 2)]):
        p, q = np.round(project(T, np.stack([a, b]))).astype(int)
        cv2.line(near, tuple(map(int, p)), tuple(map(int, q)), 1, THICKNESS + 6)
    assert not np.any(changed(image, out, tolerance=4) & (near == 0)), "pixels away from the outline and axes changed"


def test_an_outline_needs_positive_sides():
    with pytest.raises(ValueError, match="positive sides"):
        rectangle_edges(0.1, 0.0)


def test_axes_agree_with_opencvs_draw_frame_axes():
    T = facing([-0.05, 0.04, 0.5], tilt=(0.4, 0.2, -0.5))
    ours = draw_overlay(grey(), K, None, [OverlayTarget(T, SIZE)], thickness=THICKNESS)
    theirs = to_bgr8(grey())
    rvec, _ = cv2.Rodrigues(T[:3, :3])
    cv2.drawFrameAxes(theirs, K, np.zeros(5), rvec, T[:3, 3], SIZE, THICKNESS)
    for tip, color in zip(project(T, axis_segments(SIZE)[:, 1] * 0.8), AXIS_COLORS, strict=True):
        u, v = np.round(tip).astype(int)
        assert np.argmax(ours[v, u]) == np.argmax(theirs[v, u]) == np.argmax(color), (tip, ours[v, u], theirs[v, u])


def test_distortion_moves_the_drawing_with_the_lens():
    dist = np.array([-0.25, 0.05, 0.0, 0.0, 0.0])
    T = facing([0.13, 0.09, 0.45], tilt=(0.0, 0.0, 0.0))  # near the image corner: large displacement
    image = grey()
    drawn = changed(image, draw_overlay(image, K, dist, [(T, SIZE, "")], thickness=THICKNESS))
    assert all(at(drawn, p) for p in project(T, cube_edges(SIZE)[:, 0], dist))
    top = cube_edges(SIZE)[4:8, 0]  # the face nearest the camera, outermost in the image
    distorted, pinhole = project(T, top, dist), project(T, top)
    moved = np.linalg.norm(distorted - pinhole, axis=1) > 10
    assert moved.sum() >= 3
    assert not any(at(drawn, p) for p in pinhole[moved])


def test_a_target_beyond_the_view_does_not_wrap_back_through_the_distortion():
    dist = np.array([-0.25, 0.0, 0.0, 0.0, 0.0])
    T = facing([1.0, 0.0, 0.5], tilt=(0.0, 0.0, 0.0))  # 63 degrees off axis, far outside a 56 degree view
    naive = project(T, cube_edges(SIZE)[:, 0], dist)
    assert np.any((naive[:, 0] > 0) & (naive[:, 0] < W)), "the example must wrap into the image unclipped"
    image = grey()
    out = draw_overlay(image, K, dist, [(T, SIZE, "far")], thickness=THICKNESS)
    assert not changed(image, out).any()


def test_a_target_behind_the_camera_draws_nothing():
    image = grey()
    behind = facing([0.0, 0.0, -0.5])
    out = draw_overlay(image, K, np.array([-0.1, 0.01, 0.0, 0.0, 0.0]), [(behind, SIZE, "behind")])
    np.testing.assert_array_equal(out, to_bgr8(image))


def test_a_target_across_the_camera_plane_draws_only_its_front_part():
    image = grey()
    T = make_transform(matrix_from_rotvec(np.array([0.0, np.pi / 2, 0.0])), [0.0, 0.05, 0.02])  # z = 0 plane edge-on
    out = draw_overlay(image, K, None, [(T, 0.2, "across")], thickness=THICKNESS)
    assert changed(image, out).any()  # the part in front is drawn; nothing raised


def test_label_is_drawn_beside_the_target_origin():
    T = facing([0.0, 0.0, 0.5])
    plain = draw_overlay(grey(), K, None, [(T, SIZE, "")])
    labelled = draw_overlay(grey(), K, None, [(T, SIZE, "marker/7")])
    text = changed(plain, labelled)
    assert text.any()
    u, v = project(T, np.zeros((1, 3)))[0]
    rows, columns = np.nonzero(text)
    assert columns.min() >= u - 2 and columns.max() < u + 150 and rows.min() > v - 40 and rows.max() < v + 10


def test_mono_input_gives_a_bgr_copy_and_the_input_is_untouched():
    T = facing([0.0, 0.0, 0.5])
    for image in (grey(), np.full((H, W, 3), GREY, np.uint8), np.full((H, W, 4), GREY, np.uint8),
                  np.full((H, W), GREY << 8, np.uint16)):
        before = image.copy()
        out = draw_overlay(image, K, None, [(T, SIZE, "x")])
        assert out.shape == (H, W, 3) and out.dtype == np.uint8
        assert not np.shares_memory(out, image)
        np.testing.assert_array_equal(image, before)
        assert changed(image[..., :3] if image.ndim == 3 else image, out).any()
    np.testing.assert_array_equal(to_bgr8(np.full((2, 2), 0x1234, np.uint16)), np.full((2, 2, 3), 0x12, np.uint8))


def test_no_targets_is_a_plain_copy():
    image = np.random.default_rng(0).integers(0, 256, (H, W, 3), dtype=np.uint8)
    out = draw_overlay(image, K, None, [])
    np.testing.assert_array_equal(out, image)
    assert out is not image


@pytest.mark.parametrize(("image", "T", "size"), [
    (np.zeros((H, W), np.float32), np.eye(4), 0.05),
    (np.zeros((H, W, 2), np.uint8), np.eye(4), 0.05),
    (np.zeros((H, W), np.uint8), np.eye(3), 0.05),
    (np.zeros((H, W), np.uint8), np.full((4, 4), np.nan), 0.05),
    (np.zeros((H, W), np.uint8), np.eye(4), 0.0),
    (np.zeros((H, W), np.uint8), np.eye(4), float("nan")),
])
def test_unusable_inputs_are_refused(image, T, size):
    with pytest.raises(ValueError):
        draw_overlay(image, K, None, [(T, size, "")])


def test_board_cube_is_half_the_boards_smaller_side_at_least_a_marker():
    def corners(board):
        return np.concatenate([m.corners() for m in board.markers.values()])

    assert board_cube_size(corners(grid_map("b", 3, 2, 0.05, 0.05)), 0.05) == pytest.approx(0.075)
    assert board_cube_size(corners(grid_map("row", 4, 1, 0.05, 0.01)), 0.05) == pytest.approx(0.05)
    assert board_cube_size(np.zeros((0, 3)), 0.04) == 0.04
