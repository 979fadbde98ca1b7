"""Rotations and rigid transforms, cross-checked against cv2.Rodrigues and closed forms."""

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from services.geometry.rotation import (
    matrix_from_quaternion,
    matrix_from_rotvec,
    nearest_rotation,
    quaternion_from_matrix,
    rotation_angle,
    rotation_angles,
    rotvec_from_matrix,
)
from services.geometry.se3 import (
    from_quaternion_translation,
    invert,
    make_transform,
    to_quaternion_translation,
    transform_points,
)

rotvecs = st.tuples(*[st.floats(-1, 1)] * 3).map(np.array).filter(lambda v: np.linalg.norm(v) > 1e-6)
angles = st.floats(0.0, np.pi)


def rotvec(direction: np.ndarray, angle: float) -> np.ndarray:
    return direction / np.linalg.norm(direction) * angle


@settings(max_examples=200, deadline=None)
@given(rotvecs, angles)
def test_quaternion_matches_axis_angle_closed_form(direction, angle):
    v = rotvec(direction, angle)
    q = quaternion_from_matrix(matrix_from_rotvec(v))
    axis = direction / np.linalg.norm(direction)
    expected = np.array([*(np.sin(angle / 2) * axis), np.cos(angle / 2)])
    assert q[3] >= 0
    assert np.allclose(q, expected, atol=1e-9) or np.allclose(q, -expected, atol=1e-9)


@settings(max_examples=200, deadline=None)
@given(rotvecs, angles)
def test_quaternion_round_trip_and_rodrigues_agree(direction, angle):
    R = matrix_from_rotvec(rotvec(direction, angle))
    assert np.allclose(matrix_from_quaternion(quaternion_from_matrix(R)), R, atol=1e-12)
    assert np.allclose(matrix_from_rotvec(rotvec_from_matrix(R)), R, atol=1e-12)
    if 1e-3 < angle < np.pi - 1e-6:  # cv2.Rodrigues rounds tiny angles to zero; at pi, v and -v are one rotation
        assert np.allclose(rotvec_from_matrix(R), cv2.Rodrigues(R)[0].ravel(), atol=1e-6)
    assert rotation_angle(R, np.eye(3)) == pytest.approx(angle, abs=1e-12)


def test_quaternion_near_half_turn_is_accurate():
    for axis in np.eye(3):
        R = matrix_from_rotvec(axis * (np.pi - 1e-9))
        assert np.allclose(matrix_from_quaternion(quaternion_from_matrix(R)), R, atol=1e-12)


TINY = (1e-12, 1e-10, 1e-9)
"""Distances (rad) from 0 or pi that an arccos of the trace cannot see: its cosine rounds them to +-1."""


def about_the_same_angle(found: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Elementwise: ``found`` within 1e-12 of the distance of ``truth`` to 0 or pi (the nearer), or within 1e-15 rad."""
    return np.abs(found - truth) <= 1e-12 * np.minimum(truth, np.pi - truth) + 1e-15


def turns(angles: list[float]) -> np.ndarray:
    """(len(angles) * 20, 3, 3) rotations by each of ``angles`` (rad) about the same 20 random axes (scipy)."""
    axes = np.random.default_rng(0).normal(size=(20, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    return Rotation.from_rotvec((np.asarray(angles)[:, None, None] * axes).reshape(-1, 3)).as_matrix()


@pytest.mark.parametrize("angle", [*TINY, 1e-8, 1e-6, 1e-3, 0.5, 1.0, 2.0, 3.0, np.pi - 1e-6, np.pi - 1e-12, np.pi])
def test_rotation_angles_agree_with_scipy_from_tiny_angles_to_a_half_turn(angle):
    R = turns([angle])
    truth = Rotation.from_matrix(R).magnitude()
    assert np.all(about_the_same_angle(rotation_angles(R), truth))
    assert np.all(about_the_same_angle(rotation_angles(R), np.full(len(R), angle)))
    turned = Rotation.random(len(R), random_state=2).as_matrix()
    between = [rotation_angle(a, b) for a, b in zip(turned, turned @ R, strict=True)]
    assert np.allclose(between, truth, rtol=0, atol=4e-15)


def test_rotation_angles_are_accurate_where_an_arccos_of_the_trace_is_not():
    R = turns([*TINY, *(np.pi - np.asarray(TINY))])
    truth = Rotation.from_matrix(R).magnitude()
    arccos = np.arccos(np.clip((np.trace(R, axis1=1, axis2=2) - 1) / 2, -1.0, 1.0))
    assert np.all(about_the_same_angle(rotation_angles(R), truth))
    assert not np.any(about_the_same_angle(arccos, truth))


def test_rotation_angles_keep_the_leading_shape_and_name_the_expected_one():
    R = turns([*TINY, 1.0]).reshape(2, -1, 3, 3)
    assert rotation_angles(R).shape == R.shape[:2]
    assert rotation_angles(np.eye(3)).shape == ()
    with pytest.raises(ValueError, match=r"R must have shape \(\*, 3, 3\), got \(4, 4\)"):
        rotation_angles(np.eye(4))


def test_nearest_rotation_projects_noise_back_onto_so3():
    rng = np.random.default_rng(0)
    R = matrix_from_rotvec([0.3, -0.2, 0.9])
    M = R + rng.normal(0, 1e-3, (3, 3))
    P = nearest_rotation(M)
    assert np.allclose(P.T @ P, np.eye(3), atol=1e-12) and np.linalg.det(P) == pytest.approx(1.0)
    assert rotation_angle(P, R) < 2e-3
    assert np.linalg.det(nearest_rotation(-np.eye(3))) == pytest.approx(1.0)


def test_transform_compose_invert_and_points():
    rng = np.random.default_rng(1)
    T_a_b = make_transform(matrix_from_rotvec([0.1, 0.2, 0.3]), [1.0, -2.0, 0.5])
    T_b_c = make_transform(matrix_from_rotvec([-0.4, 0.0, 0.2]), [0.0, 0.3, 2.0])
    points_c = rng.normal(size=(10, 3))
    points_a = transform_points(T_a_b @ T_b_c, points_c)
    assert np.allclose(points_a, transform_points(T_a_b, transform_points(T_b_c, points_c)))
    assert np.allclose(invert(T_a_b), np.linalg.inv(T_a_b))
    q, t = to_quaternion_translation(T_a_b)
    assert np.allclose(from_quaternion_translation(q, t), T_a_b)
