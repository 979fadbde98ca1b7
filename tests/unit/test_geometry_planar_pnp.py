"""Planar PnP: IPPE candidates against OpenCV's solvePnPGeneric on noisy corners (square patch, free
planar patch, coplanar patches), scoring against cv2.projectPoints, the homography pose, plane frames."""

import cv2
import numpy as np
import pytest

from services.geometry.camera import intrinsics, project_points
from services.geometry.planar_pnp import (
    Patch,
    PlanarView,
    homography_pose,
    in_plane,
    ippe_candidates,
    plane_frame,
    reprojection_rms,
)
from services.geometry.rotation import matrix_from_rotvec
from services.geometry.se3 import invert, make_transform, transform_points

K = intrinsics(640, 480, 56.0)
H = 0.025
SQUARE = np.array([[-H, H, 0.0], [H, H, 0.0], [H, -H, 0.0], [-H, -H, 0.0]])
FACING = np.diag([1.0, -1.0, -1.0])
"""A plane frame turned to face the camera: its z towards it."""
POSES = [make_transform(matrix_from_rotvec(rotvec) @ FACING, t) for rotvec, t in [
    ([0.3, -0.2, 0.1], [0.02, -0.01, 0.4]), ([-0.6, 0.4, 2.0], [-0.05, 0.03, 0.6]),
    ([0.1, 0.9, -0.4], [0.0, 0.0, 0.25]), ([0.35, 0.15, 0.0], [0.03, 0.02, 0.7])]]
"""``T_camera_target`` poses the tests view their targets from."""


def noisy_pixels(T_camera_target: np.ndarray, points: np.ndarray, seed: int, sigma: float = 0.5) -> np.ndarray:
    exact = project_points(transform_points(T_camera_target, points), K)
    return exact + np.random.default_rng(seed).normal(0, sigma, exact.shape)


def opencv_poses(points_frame: np.ndarray, pixels: np.ndarray, flags: int,
                 T_target_frame: np.ndarray) -> tuple[list[np.ndarray], list[float]]:
    """cv2.solvePnPGeneric's solutions as ``T_camera_target`` for points given in ``frame``, and their
    reprojection errors turned into RMS residual lengths (OpenCV's is per coordinate: times sqrt 2)."""
    _, rvecs, tvecs, errors = cv2.solvePnPGeneric(points_frame, pixels, K, None, flags=flags)
    poses = [make_transform(cv2.Rodrigues(r)[0], t.ravel()) @ invert(T_target_frame) for r, t in zip(rvecs, tvecs,
                                                                                                     strict=True)]
    return poses, (np.asarray(errors).ravel() * np.sqrt(2)).tolist()


def assert_same_candidates(candidates, poses, errors, atol=1e-9):
    order = np.argsort(errors)
    assert len(candidates) == len(poses) == 2
    for candidate, k in zip(candidates, order, strict=True):
        assert np.allclose(candidate.T, poses[k], atol=atol)
        assert candidate.rms_px == pytest.approx(errors[k], rel=1e-6, abs=1e-9)
    assert candidates[0].rms_px <= candidates[1].rms_px


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("T", POSES)
def test_a_square_patch_gives_opencvs_ippe_square_candidates(T, seed):
    T_target_patch = make_transform(matrix_from_rotvec([0.0, 0.0, 0.4]), [0.1, -0.05, 0.0])
    points = transform_points(T_target_patch, SQUARE)
    pixels = noisy_pixels(T, points, seed)
    view = PlanarView(points, pixels, (Patch(T_target_patch, SQUARE, square=True),))
    (candidates,) = ippe_candidates([view], K)
    assert_same_candidates(candidates, *opencv_poses(SQUARE, pixels, cv2.SOLVEPNP_IPPE_SQUARE, T_target_patch))


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("T", POSES)
def test_a_free_planar_patch_gives_opencvs_ippe_candidates(T, seed):
    """A textured planar target: scattered points, not a square, solved with SOLVEPNP_IPPE."""
    rng = np.random.default_rng(100 + seed)
    patch_points = np.column_stack([rng.uniform(-0.06, 0.06, (10, 2)), np.zeros(10)])
    T_target_patch = make_transform(matrix_from_rotvec([0.2, -0.1, 0.3]), [0.0, 0.02, 0.01])
    points = transform_points(T_target_patch, patch_points)
    pixels = noisy_pixels(T, points, seed)
    (candidates,) = ippe_candidates([PlanarView(points, pixels, (Patch(T_target_patch, patch_points),))], K)
    assert_same_candidates(candidates, *opencv_poses(patch_points, pixels, cv2.SOLVEPNP_IPPE, T_target_patch))


def grid_patches(T_target_grid: np.ndarray) -> tuple[Patch, ...]:
    """Six square patches in a 3 x 2 grid on the plane of ``T_target_grid``."""
    return tuple(Patch(T_target_grid @ make_transform(np.eye(3), [0.07 * (c - 1), 0.07 * (0.5 - r), 0.0]), SQUARE,
                       square=True) for r in range(2) for c in range(3))


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("T", POSES)
def test_coplanar_patches_are_solved_together_as_opencvs_ippe(T, seed):
    T_target_grid = make_transform(matrix_from_rotvec([0.5, 0.0, -0.2]), [0.01, 0.0, -0.02])
    patches = grid_patches(T_target_grid)
    points = np.concatenate([transform_points(p.T_target_patch, p.points) for p in patches])
    pixels = noisy_pixels(T, points, seed)
    (candidates,) = ippe_candidates([PlanarView(points, pixels, patches)], K)
    grid_points = transform_points(invert(T_target_grid), points)
    assert np.allclose(grid_points[:, 2], 0.0)
    assert_same_candidates(candidates, *opencv_poses(grid_points, pixels, cv2.SOLVEPNP_IPPE, T_target_grid), 1e-8)


def box_view(T: np.ndarray, sigma: float, seed: int = 0) -> PlanarView:
    """Two squares on perpendicular faces of a box (front and right side), both towards the camera."""
    side = make_transform(matrix_from_rotvec([0.0, np.pi / 2, 0.0]), [0.04, 0.0, -0.04])
    patches = (Patch(np.eye(4), SQUARE, square=True), Patch(side, SQUARE, square=True))
    points = np.concatenate([transform_points(p.T_target_patch, p.points) for p in patches])
    return PlanarView(points, noisy_pixels(T, points, seed, sigma), patches)


def test_patches_on_several_planes_keep_the_best_pose_over_all_points():
    T = make_transform(matrix_from_rotvec([0.2, 0.7, 0.1]) @ FACING, [0.0, 0.02, 0.5])
    (exact,) = ippe_candidates([box_view(T, 0.0)], K)
    assert len(exact) == 1 and np.allclose(exact[0].T, T, atol=1e-7) and exact[0].rms_px < 1e-6
    view = box_view(T, 0.5, seed=3)
    (noisy,) = ippe_candidates([view], K)
    per_patch = []
    for n, patch in enumerate(view.patches):
        per_patch += opencv_poses(SQUARE, view.pixels[4 * n:4 * n + 4], cv2.SOLVEPNP_IPPE_SQUARE,
                                  patch.T_target_patch)[0]
    rms = reprojection_rms(np.array(per_patch), np.array([view.points] * len(per_patch)),
                           np.array([view.pixels] * len(per_patch)), K)
    assert len(noisy) == 1 and np.allclose(noisy[0].T, per_patch[int(np.argmin(rms))], atol=1e-9)
    assert noisy[0].rms_px == pytest.approx(rms.min())


def test_views_solved_together_get_what_each_gets_alone():
    views = [PlanarView(SQUARE, noisy_pixels(T, SQUARE, seed), (Patch(np.eye(4), SQUARE, square=True),))
             for seed, T in enumerate(POSES)]
    together = ippe_candidates(views, K)
    for view, candidates in zip(views, together, strict=True):
        (alone,) = ippe_candidates([view], K)
        assert [c.rms_px for c in candidates] == [c.rms_px for c in alone]
        assert all(np.array_equal(a.T, b.T) for a, b in zip(candidates, alone, strict=True))


def test_points_opencv_refuses_give_none():
    """SOLVEPNP_IPPE needs at least four points."""
    three = SQUARE[:3]
    view = PlanarView(three, project_points(transform_points(POSES[0], three), K), (Patch(np.eye(4), three),))
    assert ippe_candidates([view], K) == [None]


def test_reprojection_rms_matches_opencvs_projection_and_refuses_points_behind():
    rng = np.random.default_rng(7)
    points = np.concatenate([rng.uniform(-0.1, 0.1, (3, 6, 2)), rng.uniform(-0.02, 0.02, (3, 6, 1))], axis=2)
    T = np.array(POSES[:3])
    pixels = rng.uniform(0, 480, (3, 6, 2))
    rms = reprojection_rms(T, points, pixels, K)
    for k in range(3):
        projected = cv2.projectPoints(points[k], cv2.Rodrigues(T[k, :3, :3])[0], T[k, :3, 3], K, None)[0]
        expected = np.sqrt(np.mean(np.sum((projected.reshape(-1, 2) - pixels[k]) ** 2, axis=1)))
        assert rms[k] == pytest.approx(expected, rel=1e-9)
    behind = T.copy()
    behind[1, :3, 3] = (0.0, 0.0, -0.5)
    assert np.isinf(reprojection_rms(behind, points, pixels, K)).tolist() == [False, True, False]


@pytest.mark.parametrize("T", POSES)
def test_the_homography_pose_of_exact_points_is_the_pose(T):
    T_target_grid = make_transform(matrix_from_rotvec([0.5, 0.0, -0.2]), [0.01, 0.0, -0.02])
    patches = grid_patches(T_target_grid)
    points = np.concatenate([transform_points(p.T_target_patch, p.points) for p in patches])
    view = PlanarView(points, noisy_pixels(T, points, 0, 0.0), patches)
    plane = plane_frame(view)
    assert plane is not None and np.allclose(in_plane(view, plane)[:, 2], 0.0, atol=0.0)
    assert np.allclose(homography_pose(view, plane, K), T, atol=1e-8)


def test_the_plane_frame_faces_like_the_patches_and_refuses_non_coplanar_points():
    T_target_grid = make_transform(matrix_from_rotvec([0.5, 0.0, -0.2]), [0.01, 0.0, -0.02])
    patches = grid_patches(T_target_grid)
    points = np.concatenate([transform_points(p.T_target_patch, p.points) for p in patches])
    plane = plane_frame(PlanarView(points, np.zeros((len(points), 2)), patches))
    assert plane is not None and np.allclose(plane[:3, :3].T @ plane[:3, :3], np.eye(3))
    assert np.linalg.det(plane[:3, :3]) == pytest.approx(1.0)
    assert plane[:3, 2] @ T_target_grid[:3, 2] == pytest.approx(1.0)
    assert np.allclose(plane[:3, 3], points.mean(axis=0))
    lone = Patch(T_target_grid, SQUARE, square=True)
    assert plane_frame(PlanarView(transform_points(T_target_grid, SQUARE), np.zeros((4, 2)), (lone,))) is T_target_grid
    assert plane_frame(box_view(POSES[0], 0.0)) is None
