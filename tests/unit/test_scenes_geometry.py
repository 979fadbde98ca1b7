"""Geometry under the scenes: pinhole helpers, trajectories and plane warping, cross-checked with OpenCV."""

import cv2
import numpy as np
import pytest

from services.geometry.camera import (
    clip_polygon_near,
    intrinsics,
    look_at,
    pixel_rays,
    plane_homography,
    project_points,
)
from services.geometry.rotation import matrix_from_rotvec
from services.geometry.se3 import invert, make_transform, transform_points
from services.geometry.trajectory import LookAtPath, RigidPath, SinePath
from services.synthetic.plane import PlaneTexture

K = intrinsics(640, 480, 60.0)
DIST = np.array([-0.07, 0.015, 4e-4, -3e-4, 0.0])


def test_intrinsics_field_of_view():
    assert K[0, 0] == pytest.approx(320 / np.tan(np.radians(30)))
    assert (K[0, 2], K[1, 2]) == (319.5, 239.5)


def test_look_at_puts_the_target_on_the_principal_point_with_up_at_the_top():
    eye, target, up = np.array([1.0, -2.0, 0.5]), np.array([0.2, 0.3, 1.7]), np.array([0.0, 0.0, 1.0])
    T_world_cam = look_at(eye, target, up)
    R = T_world_cam[:3, :3]
    assert np.allclose(R.T @ R, np.eye(3)) and np.linalg.det(R) == pytest.approx(1.0)
    pixel = project_points(transform_points(invert(T_world_cam), target), K)[0]
    assert np.allclose(pixel, K[:2, 2])
    above = project_points(transform_points(invert(T_world_cam), target + 0.1 * up), K)[0]
    assert above[1] < pixel[1] and above[0] == pytest.approx(pixel[0])
    with pytest.raises(ValueError, match="parallel"):
        look_at(eye, eye + up, up)


def test_plane_homography_matches_project_points():
    T_cam_plane = make_transform(matrix_from_rotvec([0.3, -0.4, 0.2]), [0.1, -0.05, 1.2])
    plane_points = np.random.default_rng(0).uniform(-0.3, 0.3, (20, 2))
    mapped = cv2.perspectiveTransform(plane_points.reshape(-1, 1, 2), plane_homography(K, T_cam_plane)).reshape(-1, 2)
    projected = project_points(transform_points(T_cam_plane, np.column_stack([plane_points, np.zeros(20)])), K)
    assert np.allclose(mapped, projected, atol=1e-9)


def test_pixel_rays_invert_the_distorted_projection():
    rays = pixel_rays(K, DIST, 640, 480)
    assert rays.shape == (480, 640, 3) and np.allclose(np.linalg.norm(rays, axis=2), 1.0, atol=1e-6)
    v, u = np.mgrid[0:480:37, 0:640:41]
    reprojected = project_points(rays[v.ravel(), u.ravel()].astype(np.float64), K, DIST)
    assert np.abs(reprojected - np.column_stack([u.ravel(), v.ravel()])).max() < 1e-3


def test_clip_polygon_near_keeps_the_part_in_front():
    square = np.array([[-1.0, 0.0, -1.0], [1.0, 0.0, -1.0], [1.0, 0.0, 3.0], [-1.0, 0.0, 3.0]])
    clipped = clip_polygon_near(square, 1.0)
    assert len(clipped) == 4 and np.all(clipped[:, 2] >= 1.0 - 1e-12)
    assert {tuple(p) for p in np.round(clipped, 9)} == {(-1, 0, 1), (1, 0, 1), (1, 0, 3), (-1, 0, 3)}
    assert len(clip_polygon_near(square, 5.0)) == 0
    assert np.array_equal(clip_polygon_near(square, -2.0), square)


def test_sine_path_stays_within_its_amplitude_and_is_smooth():
    path = SinePath.random(np.random.default_rng(1), (1.0, 2.0), (0.5, 0.1), (2.0, 5.0), terms=3)
    samples = np.array([path(t) for t in np.linspace(0, 60, 6001)])
    assert np.all(np.abs(samples - (1.0, 2.0)) <= (0.5, 0.1))
    assert np.ptp(samples[:, 0]) > 0.5
    assert np.abs(np.diff(samples, axis=0)).max() < 0.01


def test_look_at_path_rolls_about_the_view_axis():
    rng = np.random.default_rng(2)
    eye, target = SinePath.random(rng, (0, 0, 1), (0.2, 0.2, 0.1), (3, 6)), SinePath.random(rng, (0, 0, 0), 0.0, (3, 6))
    unrolled = LookAtPath(eye, target, SinePath.random(rng, (0.0,), (0.0,), (3, 6)), np.array([0.0, 1.0, 0.0]))
    rolled = LookAtPath(eye, target, SinePath(np.array([0.3]), np.zeros((1, 1)), np.ones((1, 1)), np.zeros((1, 1))),
                        np.array([0.0, 1.0, 0.0]))
    a, b = unrolled.pose(1.3), rolled.pose(1.3)
    assert np.allclose(a[:3, 2], b[:3, 2]) and np.allclose(a[:3, 3], b[:3, 3])
    assert np.degrees(np.arccos(a[:3, 0] @ b[:3, 0])) == pytest.approx(np.degrees(0.3))


def test_rigid_path_pose():
    rng = np.random.default_rng(3)
    path = RigidPath(SinePath.random(rng, (0, 0, 2), 0.3, (3, 6)), SinePath.random(rng, (0, 0, 0), 0.5, (3, 6)),
                     matrix_from_rotvec([0.0, 0.0, 1.0]))
    T = path.pose(0.7)
    assert np.allclose(T[:3, 3], path.position(0.7))
    assert np.allclose(T[:3, :3], matrix_from_rotvec(path.rotvec(0.7)) @ matrix_from_rotvec([0, 0, 1]))


@pytest.mark.parametrize("distance", [0.4, 1.5, 6.0])
def test_plane_warp_puts_texels_where_the_pose_projects_them(distance):
    """A disc in the texture is rendered where its outline projects, whatever the pyramid level.

    Compared: the rendered blob's intensity centroid and the area centroid of the disc's
    projected outline (the exact perspective image of the disc, not of its centre).
    """
    texture = np.zeros((512, 768), np.uint8)
    centre, radius = (301, 187), 12  # texels
    cv2.circle(texture, (centre[0] * 16, centre[1] * 16), radius * 16, 255, -1, cv2.LINE_AA, 4)
    plane = PlaneTexture(texture, 0.6, 0.4)
    T_cam_plane = make_transform(matrix_from_rotvec([0.25, -0.35, 0.1]) @ np.diag([1.0, -1.0, -1.0]),
                                 [0.02, -0.01, distance])
    image = plane.warp(K, T_cam_plane, (640, 480), border_value=0).astype(np.float64)
    angles = np.linspace(0, 2 * np.pi, 720, endpoint=False)
    outline = np.column_stack([centre[0] + (radius - 0.5) * np.cos(angles), centre[1] + (radius - 0.5) * np.sin(angles),
                               np.ones(720)])
    outline = (np.linalg.solve(plane.texel_from_plane, outline.T).T)[:, :2]
    outline_px = project_points(transform_points(T_cam_plane, np.column_stack([outline, np.zeros(720)])), K)
    moments = cv2.moments(outline_px.astype(np.float32))
    expected = np.array([moments["m10"], moments["m01"]]) / moments["m00"]
    u0, v0 = np.round(expected).astype(int)
    half = int(np.ptp(outline_px, axis=0).max()) + 6
    v, u = np.mgrid[v0 - half:v0 + half + 1, u0 - half:u0 + half + 1]
    window = image[v0 - half:v0 + half + 1, u0 - half:u0 + half + 1]
    centroid = np.array([(window * u).sum(), (window * v).sum()]) / window.sum()
    level = plane.level_at(plane.image_from_texel(K, T_cam_plane), (319.5, 239.5))
    assert level == {0.4: 0, 1.5: 2, 6.0: 4}[distance]
    assert np.linalg.norm(centroid - expected) < 0.1
