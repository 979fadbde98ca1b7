"""Two-view geometry (``services.slam.two_view``) against references computed independently here."""

import numpy as np
import pytest

from services.geometry.camera import intrinsics, project_points
from services.geometry.rotation import matrix_from_rotvec
from services.geometry.se3 import make_transform, transform_points
from services.slam.two_view import ray_parallax_deg, triangulate_pair

K = intrinsics(640, 480, 64.0)


def true_parallax_deg(points_a: np.ndarray, centre_b: np.ndarray) -> np.ndarray:
    """Plain loop: the angle at each point (view a's frame) between its directions to the two centres."""
    angles = []
    for point in points_a:
        to_a, to_b = -point, centre_b - point
        cos = to_a @ to_b / (np.linalg.norm(to_a) * np.linalg.norm(to_b))
        angles.append(np.degrees(np.arccos(min(max(cos, -1.0), 1.0))))
    return np.array(angles)


@pytest.mark.parametrize("seed", range(4))
def test_ray_parallax_is_the_angle_each_point_sees_the_baseline_under(seed):
    rng = np.random.default_rng(seed)
    points_a = np.column_stack([rng.uniform(-2.0, 2.0, (300, 2)), rng.uniform(1.0, 8.0, 300)])
    T_b_a = make_transform(matrix_from_rotvec(rng.normal(0.0, 0.1, 3)), rng.normal(0.0, 0.2, 3))
    pixels_a, pixels_b = project_points(points_a, K), project_points(transform_points(T_b_a, points_a), K)
    found = ray_parallax_deg(T_b_a[:3, :3], K, pixels_a, pixels_b)
    centre_b = -T_b_a[:3, :3].T @ T_b_a[:3, 3]
    np.testing.assert_allclose(found, true_parallax_deg(points_a, centre_b), atol=1e-6)
    triangulated = triangulate_pair(K, T_b_a, pixels_a, pixels_b).points
    np.testing.assert_allclose(found, true_parallax_deg(triangulated, centre_b), atol=1e-6)


def test_ray_parallax_of_a_rotation_is_zero():
    rng = np.random.default_rng(7)
    points_a = np.column_stack([rng.uniform(-2.0, 2.0, (100, 2)), rng.uniform(1.0, 8.0, 100)])
    R = matrix_from_rotvec([0.05, -0.12, 0.03])
    pixels_b = project_points(points_a @ R.T, K)
    np.testing.assert_allclose(ray_parallax_deg(R, K, project_points(points_a, K), pixels_b), 0.0, atol=1e-5)
