"""LM pose refinement: against cv2.solvePnPRefineLM, its Jacobian against finite differences, its
covariance against the Monte-Carlo spread of poses under known pixel noise, and the batched
refinement against the plain step-by-step loop, problem by problem."""

import cv2
import numpy as np
import pytest

from services.geometry.camera import project_points
from services.geometry.homography import DegenerateError
from services.geometry.refine import (
    augmented_rows,
    damped_steps,
    increments,
    normal_equations,
    point_basis,
    pose_covariance,
    pose_covariances,
    refine_pose,
    refine_poses,
    residuals_and_jacobian,
    residuals_and_jacobians,
)
from services.geometry.rotation import matrix_from_rotvec, rotation_angle, rotvec_from_matrix
from services.geometry.se3 import invert, make_transform, transform_points

K = np.array([[600.0, 0.0, 319.5], [0.0, 600.0, 239.5], [0.0, 0.0, 1.0]])
SQUARE = np.array([[-0.05, 0.05, 0.0], [0.05, 0.05, 0.0], [0.05, -0.05, 0.0], [-0.05, -0.05, 0.0]])


def random_pose(rng: np.random.Generator) -> np.ndarray:
    return make_transform(matrix_from_rotvec(rng.uniform(-0.6, 0.6, 3)), [*rng.uniform(-0.1, 0.1, 2),
                                                                           rng.uniform(0.4, 1.5)])


def perturbed(T: np.ndarray, rng: np.random.Generator, angle: float = 0.05, shift: float = 0.01) -> np.ndarray:
    return T @ make_transform(matrix_from_rotvec(rng.normal(0, angle, 3)), rng.normal(0, shift, 3))


def pixels_of(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    return project_points(transform_points(T, points), K)


@pytest.mark.parametrize("seed", range(10))
@pytest.mark.parametrize("planar", [False, True])
def test_agrees_with_cv2_solvepnp_refine_lm(seed, planar):
    rng = np.random.default_rng(seed)
    T = random_pose(rng)
    points = SQUARE if planar else rng.uniform(-0.1, 0.1, (10, 3))
    pixels = pixels_of(T, points) + rng.normal(0, 0.5, (len(points), 2))
    start = perturbed(T, rng)
    ours = refine_pose(start, points, pixels, K)
    rvec, tvec = cv2.solvePnPRefineLM(points, pixels, K, None, cv2.Rodrigues(start[:3, :3])[0],
                                      start[:3, 3].reshape(3, 1).copy(),
                                      criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-15))
    theirs = make_transform(matrix_from_rotvec(rvec), tvec)
    # OpenCV's LM stops a little earlier on flat cost valleys (four coplanar points): where the
    # two differ, ours always has the lower cost; they agree to 1e-5 rad and 1e-6 m.
    cost = {name: np.sum((pixels_of(T_found, points) - pixels) ** 2) for name, T_found in (("ours", ours.T),
                                                                                         ("theirs", theirs))}
    assert ours.converged
    assert cost["ours"] <= cost["theirs"] * (1 + 1e-12)
    assert rotation_angle(ours.T[:3, :3], theirs[:3, :3]) < (1e-6 if not planar else 1e-5)
    assert np.allclose(ours.T[:3, 3], theirs[:3, 3], atol=1e-6)
    assert ours.rms_px == pytest.approx(np.sqrt(cost["ours"] / len(points)), rel=1e-9)


@pytest.mark.parametrize("seed", range(5))
def test_exact_data_gives_the_true_pose(seed):
    rng = np.random.default_rng(10 + seed)
    T = random_pose(rng)
    result = refine_pose(perturbed(T, rng, 0.2, 0.03), SQUARE, pixels_of(T, SQUARE), K)
    assert result.converged and result.rms_px < 1e-8
    assert np.allclose(result.T[:3, :3], T[:3, :3], atol=1e-9)
    assert np.allclose(result.T[:3, 3], T[:3, 3], atol=1e-10)


@pytest.mark.parametrize("seed", range(5))
def test_analytic_jacobian_matches_finite_differences(seed):
    rng = np.random.default_rng(20 + seed)
    K_skewed = np.array([[610.0, 2.5, 300.0], [0.0, 590.0, 250.0], [0.0, 0.0, 1.0]])
    T, points = random_pose(rng), rng.uniform(-0.1, 0.1, (6, 3))
    pixels = rng.uniform(0, 640, (6, 2))

    def residuals(delta: np.ndarray) -> np.ndarray:
        moved = T @ make_transform(matrix_from_rotvec(delta[3:]), delta[:3])
        p = transform_points(moved, points)
        return ((p / p[:, 2:]) @ K_skewed.T)[:, :2].ravel() - pixels.ravel()

    r, J = residuals_and_jacobian(T, points, pixels, K_skewed)
    h = 1e-6
    numeric = np.column_stack([(residuals(h * e) - residuals(-h * e)) / (2 * h) for e in np.eye(6)])
    assert np.allclose(r, residuals(np.zeros(6)), atol=1e-9)
    assert np.allclose(J, numeric, rtol=1e-5, atol=1e-4 * np.abs(J).max())


def test_covariance_matches_the_monte_carlo_spread():
    rng = np.random.default_rng(5)
    sigma = 0.5
    T = make_transform(matrix_from_rotvec([0.4, -0.3, 0.1]), [0.03, -0.02, 0.6])
    exact = pixels_of(T, SQUARE)
    deltas = []
    for _ in range(400):
        found = refine_pose(T, SQUARE, exact + rng.normal(0, sigma, exact.shape), K).T
        D = invert(T) @ found
        deltas.append(np.concatenate([D[:3, 3], rotvec_from_matrix(D[:3, :3])]))
    empirical = np.cov(np.array(deltas).T)
    _, J = residuals_and_jacobian(T, SQUARE, exact, K)
    predicted = pose_covariance(J, sigma)
    assert predicted.shape == (6, 6) and np.allclose(predicted, predicted.T)
    assert np.all(np.abs(np.diag(empirical) / np.diag(predicted) - 1) < 0.3)
    scale = np.sqrt(np.outer(np.diag(predicted), np.diag(predicted)))
    assert np.max(np.abs(empirical - predicted) / scale) < 0.15


def test_covariance_scales_with_the_noise_and_needs_a_full_rank_jacobian():
    _, J = residuals_and_jacobian(make_transform(np.eye(3), [0, 0, 0.5]), SQUARE, np.zeros((4, 2)), K)
    assert np.allclose(pose_covariance(J, 2.0), 4 * pose_covariance(J, 1.0))
    J[:, 5] = 0.0
    with pytest.raises(DegenerateError):
        pose_covariance(J, 1.0)


def test_a_start_behind_the_camera_is_refused():
    T = make_transform(np.eye(3), [0, 0, -0.5])
    with pytest.raises(ValueError, match="behind"):
        refine_pose(T, SQUARE, np.zeros((4, 2)), K)


def test_too_few_points_are_refused():
    with pytest.raises(DegenerateError):
        refine_pose(make_transform(np.eye(3), [0, 0, 0.5]), SQUARE[:2], np.zeros((2, 2)), K)


def test_the_iteration_limit_is_reported():
    rng = np.random.default_rng(3)
    T = random_pose(rng)
    result = refine_pose(perturbed(T, rng, 0.3, 0.05), SQUARE, pixels_of(T, SQUARE), K, max_iterations=1)
    assert result.iterations == 1 and not result.converged
    assert result.jacobian.shape == (8, 6)


def noisy_problems(seed: int, count: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``count`` marker-like problems: (B, 4, 4) starts near the true poses, (B, 4, 3) squares of
    varied size and (B, 4, 2) pixels with 0.5 px noise."""
    rng = np.random.default_rng(seed)
    truth = [random_pose(rng) for _ in range(count)]
    squares = SQUARE * rng.uniform(0.2, 1.5, (count, 1, 1))
    pixels = np.array([pixels_of(T, X) for T, X in zip(truth, squares, strict=True)])
    return np.array([perturbed(T, rng) for T in truth]), squares, pixels + rng.normal(0, 0.5, pixels.shape)


def step_by_step(T: np.ndarray, points: np.ndarray, pixels: np.ndarray) -> tuple[np.ndarray, int, bool, int]:
    """The documented LM run one step after the other with the module's own arithmetic: the pose,
    iterations, convergence, and the longest streak of rejected steps."""
    basis, pixels = point_basis(points[None]), pixels[None]
    normal = normal_equations(augmented_rows(T[None], basis, pixels, K)[0])
    damping, iterations, streak, longest = 1e-3, 0, 0, 0
    while iterations < 100:
        iterations += 1
        step = damped_steps(normal, np.array([damping]))[0]
        candidate = T[None] @ increments(step)
        rows, front = augmented_rows(candidate, basis, pixels, K)
        candidate_normal = normal_equations(rows)
        cost, candidate_cost = normal[0, 6, 6], candidate_normal[0, 6, 6] if front[0] else np.inf
        done = np.max(np.abs(step)) < 1e-10
        if candidate_cost <= cost:
            done = done or cost - candidate_cost <= 1e-10 * cost
            T, normal, damping, streak = candidate[0], candidate_normal, max(damping / 10, 1e-12), 0
        else:
            damping, streak = damping * 10, streak + 1
            longest = max(longest, streak)
            done = done or damping > 1e12
        if done:
            return T, iterations, True, longest
    return T, iterations, False, longest


def test_a_batch_takes_every_problem_through_its_own_steps():
    """The batch (several dampings tried at once after a rejection) lands each problem exactly where
    the plain step-by-step loop does, after as many iterations."""
    starts, squares, pixels = noisy_problems(30, 40)
    batch = refine_poses(starts, squares, pixels, K)
    longest = 0
    for b in range(len(starts)):
        T, iterations, converged, streak = step_by_step(starts[b], squares[b], pixels[b])
        longest = max(longest, streak)
        assert np.array_equal(batch.T[b], T)
        assert (batch.iterations[b], batch.converged[b]) == (iterations, converged)
        alone = refine_pose(starts[b], squares[b], pixels[b], K)
        assert np.array_equal(alone.T, T) and alone.iterations == iterations
        assert batch.rms_px[b] == pytest.approx(alone.rms_px, rel=1e-12)
        assert np.allclose(batch.normal[b], alone.jacobian.T @ alone.jacobian, rtol=1e-9)
    assert longest >= 3, "no rejection streak exercised the tries of several dampings at once"
    assert not np.any(batch.degenerate)


def test_a_degenerate_problem_stops_alone():
    """All points at the object's origin leave the rotation free: that problem is flagged, the others
    are refined as if it were not there (and refine_pose raises for it)."""
    starts, squares, pixels = noisy_problems(31, 3)
    squares[1] = 0.0
    batch = refine_poses(starts, squares, pixels, K)
    assert batch.degenerate.tolist() == [False, True, False]
    assert batch.converged.tolist() == [True, False, True]
    for b in (0, 2):
        assert np.array_equal(batch.T[b], refine_pose(starts[b], squares[b], pixels[b], K).T)
    with pytest.raises(DegenerateError):
        refine_pose(starts[1], squares[1], pixels[1], K)


def test_batched_residuals_covariances_and_iteration_limits():
    starts, squares, pixels = noisy_problems(32, 4)
    r, J = residuals_and_jacobians(starts, squares, pixels, K)
    for b in range(4):
        r_b, J_b = residuals_and_jacobian(starts[b], squares[b], pixels[b], K)
        assert np.array_equal(r[b], r_b) and np.array_equal(J[b], J_b)
    normal = J.transpose(0, 2, 1) @ J
    normal[3, :, 5] = normal[3, 5, :] = 0.0
    covariance, regular = pose_covariances(normal, 0.5)
    assert regular.tolist() == [True, True, True, False] and np.all(np.isnan(covariance[3]))
    for b in range(3):
        assert np.allclose(covariance[b], pose_covariance(J[b], 0.5), rtol=1e-12, atol=0)
    limited = refine_poses(starts, squares, pixels, K, max_iterations=2)
    assert limited.iterations.tolist() == [2, 2, 2, 2] and not np.any(limited.converged)
