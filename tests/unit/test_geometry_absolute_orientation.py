"""Absolute orientation: closed forms, the two methods against each other and scipy, an honest covariance."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from services.geometry.absolute_orientation import (
    fit_rigid,
    least_squares_transform,
    least_squares_transforms,
    pose_covariance,
    pose_jacobians,
    three_point_transform,
)
from services.geometry.evaluation import pose_error
from services.geometry.rotation import matrix_from_rotvec, rotvec_from_matrix
from services.geometry.se3 import make_transform, transform_points
from services.synthetic.ir_rig import LAYOUTS


def random_pose(rng: np.random.Generator) -> np.ndarray:
    """A uniformly drawn rotation (scipy) and a translation within 2 m."""
    return make_transform(Rotation.random(random_state=rng).as_matrix(), rng.uniform(-2.0, 2.0, 3))


@pytest.mark.parametrize("seed", range(5))
def test_known_transform_is_recovered_exactly(seed):
    rng = np.random.default_rng(seed)
    T = random_pose(rng)
    body = rng.uniform(-0.1, 0.1, (6, 3))
    world = transform_points(T, body)
    fit = fit_rigid(body, world)
    assert np.allclose(fit.T_world_body, T, atol=1e-12)
    assert fit.residual_rms < 1e-12 and fit.count == 6 and fit.covariance is None
    assert np.allclose(three_point_transform(body[:3], world[:3]), T, atol=1e-12)


@pytest.mark.parametrize("seed", range(5))
def test_three_point_and_least_squares_agree_on_three_exact_points(seed):
    rng = np.random.default_rng(10 + seed)
    T = random_pose(rng)
    body = rng.uniform(-0.1, 0.1, (3, 3))
    world = transform_points(T, body)
    a = fit_rigid(body, world, method="three_point").T_world_body
    b = fit_rigid(body, world, method="svd").T_world_body
    rotation, translation = pose_error(a, b)
    assert rotation < 1e-12 and translation < 1e-12


def test_least_squares_matches_scipy_kabsch_on_noisy_points():
    rng = np.random.default_rng(3)
    T = random_pose(rng)
    body = LAYOUTS["glove"]
    world = transform_points(T, body) + rng.normal(0.0, 0.002, body.shape)
    ours = least_squares_transform(body, world)
    rotation, _ = Rotation.align_vectors(world - world.mean(axis=0), body - body.mean(axis=0))
    assert np.allclose(ours[:3, :3], rotation.as_matrix(), atol=1e-10)
    assert np.allclose(ours[:3, 3], world.mean(axis=0) - rotation.as_matrix() @ body.mean(axis=0), atol=1e-10)


def test_mirrored_points_still_give_a_proper_rotation():
    body = LAYOUTS["head"]
    fit = fit_rigid(body, body * np.array([-1.0, 1.0, 1.0]))
    assert np.isclose(np.linalg.det(fit.T_world_body[:3, :3]), 1.0)
    assert fit.residual_rms > 0.01


@pytest.mark.parametrize(("body", "world", "kwargs", "message"), [
    (np.zeros((3, 2)), np.zeros((3, 3)), {}, r"points_body must have shape \(N, 3\), got \(3, 2\)"),
    (np.eye(3), np.eye(4, 3), {}, "matched row by row"),
    (np.eye(3)[:2], np.eye(3)[:2], {}, "at least 3"),
    ([[0, 0, 0], [1, 0, 0], [2, 0, 0]], np.eye(3), {}, "one line"),
    (np.eye(3), np.eye(3), {"method": "dlt"}, "unknown absolute orientation method"),
    (np.eye(4, 3), np.eye(4, 3), {"method": "three_point"}, "exactly 3"),
    (np.eye(3), np.eye(3), {"covariances": np.zeros((2, 3, 3))}, r"covariances must have shape \(3, 3, 3\)"),
])
def test_bad_input_is_refused_with_a_reason(body, world, kwargs, message):
    with pytest.raises(ValueError, match=message):
        fit_rigid(np.asarray(body, float), np.asarray(world, float), **kwargs)


def test_three_point_refuses_a_collinear_world_triangle():
    with pytest.raises(ValueError, match="points_world: the three points are collinear"):
        three_point_transform(np.eye(3), np.array([[0.0, 0, 0], [1, 0, 0], [3, 0, 0]]))


def test_jacobians_match_finite_differences():
    rng = np.random.default_rng(4)
    T = random_pose(rng)
    body = LAYOUTS["tool"]
    J = pose_jacobians(T, body)
    step = 1e-7
    for k in range(6):
        delta = np.zeros(6)
        delta[k] = step
        moved = make_transform(matrix_from_rotvec(delta[:3]) @ T[:3, :3], T[:3, 3] + delta[3:])
        numeric = (transform_points(moved, body) - transform_points(T, body)) / step
        assert np.allclose(J[:, :, k], numeric, atol=1e-6)


def test_isotropic_covariance_equals_the_inverse_information():
    rng = np.random.default_rng(5)
    T = random_pose(rng)
    body = LAYOUTS["glove"]
    sigma = np.tile(np.eye(3) * 1e-6, (len(body), 1, 1))
    J = pose_jacobians(T, body)
    information = np.einsum("nki,nkl,nlj->ij", J, np.linalg.inv(sigma), J)
    assert np.allclose(pose_covariance(T, body, sigma), np.linalg.inv(information), rtol=1e-9, atol=1e-20)


@pytest.mark.parametrize("name", ["wand", "glove"])
def test_covariance_predicts_the_monte_carlo_spread(name):
    """Anisotropic point noise (each point its own covariance, elongated as a triangulated point's): the
    spread of the fitted poses matches the stated covariance within 30 % along every direction."""
    rng = np.random.default_rng(6)
    T = make_transform(matrix_from_rotvec(np.array([0.4, -0.8, 0.3])), np.array([0.2, -0.1, 2.2]))
    body = LAYOUTS[name]
    world = transform_points(T, body)
    axes = np.stack([matrix_from_rotvec(rng.normal(0.0, 1.0, 3)) for _ in body])
    scales = np.array([0.0002, 0.0002, 0.0008])
    sigma = np.einsum("nij,j,nkj->nik", axes, scales**2, axes)
    predicted = fit_rigid(body, world, sigma).covariance
    assert predicted is not None
    trials = 4000
    chol = np.linalg.cholesky(sigma)
    errors = np.empty((trials, 6))
    for k in range(trials):
        noisy = world + np.einsum("nij,nj->ni", chol, rng.normal(size=body.shape))
        estimate = fit_rigid(body, noisy).T_world_body
        errors[k, :3] = rotvec_from_matrix(T[:3, :3] @ estimate[:3, :3].T)
        errors[k, 3:] = T[:3, 3] - estimate[:3, 3]
    sample = np.cov(errors.T)
    whiten = np.linalg.inv(np.linalg.cholesky(predicted))
    spread = np.sqrt(np.linalg.eigvalsh(whiten @ sample @ whiten.T))
    assert np.all((spread > 0.7) & (spread < 1.3)), spread


def test_many_sets_at_once_equal_one_at_a_time():
    """Sets with their own subsets of pairs (some with a reflection to remove) give what each gives alone."""
    rng = np.random.default_rng(21)
    body = rng.uniform(-0.1, 0.1, (8, 5, 3))
    world = np.array([transform_points(random_pose(rng), b) for b in body]) + rng.normal(0.0, 0.002, (8, 5, 3))
    world[3] = world[3] * np.array([1.0, 1.0, -1.0])
    used = np.ones((8, 5), bool)
    used[1, 2] = used[4, 0] = used[5, 4] = used[5, 3] = False
    transforms, rms = least_squares_transforms(body, world, used)
    for k in range(len(body)):
        alone = fit_rigid(body[k][used[k]], world[k][used[k]])
        np.testing.assert_allclose(transforms[k], alone.T_world_body, atol=1e-12)
        assert rms[k] == pytest.approx(alone.residual_rms, rel=1e-9)
    with pytest.raises(ValueError, match="at least 3"):
        least_squares_transforms(body[:1, :2], world[:1, :2])
