"""Trajectory evaluation: Umeyama alignment, ATE, RPE and stamp association, on hand-computed cases
and against scipy."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from services.geometry.evaluation import (
    Similarity,
    absolute_trajectory_error,
    apply_similarity,
    associate,
    error_stats,
    relative_pose_error,
    rpe_pairs,
    score_trajectory,
    umeyama,
)
from services.geometry.rotation import matrix_from_rotvec
from services.geometry.se3 import make_transform


def random_poses(rng: np.random.Generator, n: int) -> np.ndarray:
    """(n, 4, 4) poses: a random walk of positions (m) and rotations."""
    positions = np.cumsum(rng.normal(0, 0.3, (n, 3)), axis=0)
    return np.array([make_transform(matrix_from_rotvec(rng.normal(0, 1.0, 3)), p) for p in positions])


def line_poses(steps: list[float], yaw_per_step: float = 0.0) -> np.ndarray:
    """Poses walking along their own x axis by ``steps`` (m), turning ``yaw_per_step`` (rad) about z after each."""
    poses = [np.eye(4)]
    for step in steps:
        motion = make_transform(matrix_from_rotvec([0.0, 0.0, yaw_per_step]), [step, 0.0, 0.0])
        poses.append(poses[-1] @ motion)
    return np.array(poses)


def known_similarity(rng: np.random.Generator, s: float = 1.0) -> Similarity:
    return Similarity(Rotation.random(random_state=rng.integers(1 << 31)).as_matrix(), rng.normal(0, 5, 3), s)


@pytest.mark.parametrize("with_scale", [False, True])
def test_umeyama_recovers_a_known_similarity_exactly(with_scale):
    rng = np.random.default_rng(1)
    points = rng.normal(0, 2, (30, 3))
    truth = known_similarity(rng, 0.37 if with_scale else 1.0)
    found = umeyama(points, truth.apply(points), with_scale=with_scale)
    assert np.allclose(found.R, truth.R, atol=1e-12) and np.allclose(found.t, truth.t, atol=1e-10)
    assert found.s == pytest.approx(truth.s, abs=1e-12)
    assert np.allclose(found.matrix @ np.append(points[0], 1.0), np.append(truth.apply(points[:1])[0], 1.0))


def test_umeyama_rotation_agrees_with_scipy_align_vectors_on_noisy_points():
    rng = np.random.default_rng(2)
    points = rng.normal(0, 1, (50, 3))
    target = known_similarity(rng, 2.5).apply(points) + rng.normal(0, 0.05, points.shape)
    found = umeyama(points, target, with_scale=True)
    rotation, _ = Rotation.align_vectors(target - target.mean(axis=0), points - points.mean(axis=0))
    assert np.allclose(found.R, rotation.as_matrix(), atol=1e-9)
    # the scale and translation are the least-squares ones given R: a nudge of either makes the fit worse
    def cost(s: float, t: np.ndarray) -> float:
        return float(np.sum((target - (s * points @ found.R.T + t)) ** 2))

    best = cost(found.s, found.t)
    assert all(cost(found.s + ds, found.t) > best for ds in (-1e-4, 1e-4))
    assert all(cost(found.s, found.t + dt) > best for dt in np.eye(3) * 1e-4)


def test_umeyama_returns_a_proper_rotation_for_mirrored_points():
    rng = np.random.default_rng(3)
    points = rng.normal(0, 1, (20, 3))
    found = umeyama(points, points * [1.0, 1.0, -1.0])
    assert np.linalg.det(found.R) == pytest.approx(1.0)
    assert np.allclose(found.R.T @ found.R, np.eye(3), atol=1e-12)


def test_umeyama_refuses_too_few_points_or_a_bad_shape():
    with pytest.raises(ValueError, match="at least 2 matched positions, got 1"):
        umeyama(np.zeros((1, 3)), np.zeros((1, 3)))
    with pytest.raises(ValueError, match=r"source must be \(N, 3\) positions or \(N, 4, 4\) poses, got shape \(5, 2\)"):
        umeyama(np.zeros((5, 2)), np.zeros((5, 3)))
    with pytest.raises(ValueError, match="not all the same point"):
        umeyama(np.ones((4, 3)), np.zeros((4, 3)), with_scale=True)
    with pytest.raises(ValueError, match="matched row by row: 4 against 5 rows"):
        umeyama(np.zeros((4, 3)), np.zeros((5, 3)))


def test_ate_of_a_known_offset_is_the_offset_unaligned_and_zero_aligned():
    gt = random_poses(np.random.default_rng(4), 40)
    est = gt.copy()
    est[:, :3, 3] += [0.03, -0.04, 0.0]
    assert absolute_trajectory_error(est, gt, "none").stats.rmse == pytest.approx(0.05, abs=1e-12)
    aligned = absolute_trajectory_error(est, gt, "se3")
    assert aligned.stats.max < 1e-12 and np.allclose(aligned.alignment.t, [-0.03, 0.04, 0.0])


def test_ate_figures_are_the_hand_computed_ones():
    gt = np.zeros((4, 3))
    est = np.array([[0.1, 0, 0], [0, 0.2, 0], [0, 0, 0.3], [0.4, 0, 0]])
    stats = absolute_trajectory_error(est, gt, "none").stats
    assert stats.rmse == pytest.approx(math.sqrt((0.01 + 0.04 + 0.09 + 0.16) / 4))
    assert (stats.mean, stats.median, stats.max, stats.count) == pytest.approx((0.25, 0.25, 0.4, 4))


def test_sim3_ate_undoes_a_known_similarity_and_reports_its_scale():
    rng = np.random.default_rng(5)
    gt = random_poses(rng, 60)
    to_est = known_similarity(rng, 0.2)
    est = apply_similarity(to_est, gt)
    ate = absolute_trajectory_error(est, gt, "sim3")
    assert ate.stats.max < 1e-9 and ate.alignment.s == pytest.approx(5.0, rel=1e-12)
    assert np.allclose(ate.alignment.R, to_est.R.T, atol=1e-12)
    assert absolute_trajectory_error(est, gt, "se3").stats.rmse > 0.1  # the scale is not undone without sim3
    back = apply_similarity(ate.alignment, est)
    assert np.allclose(back, gt, atol=1e-9)  # rotations too: apply_similarity keeps them proper


def test_rpe_of_a_stretched_and_turning_estimate_is_the_hand_computed_one():
    gt = line_poses([1.0] * 10)
    est = line_poses([1.1] * 10, yaw_per_step=math.radians(1.0))
    one = relative_pose_error(est, gt, 1)
    assert np.allclose(one.rotation, math.radians(1.0), atol=1e-12)
    assert np.allclose(one.translation, 0.1, atol=1e-12) and len(one.pairs) == 10
    three = relative_pose_error(est, gt, 3)
    assert np.allclose(three.rotation, math.radians(3.0), atol=1e-12) and len(three.pairs) == 8
    # over 3 steps the estimate walks 1.1 m, turns 1 deg, 1.1 m, turns, 1.1 m: its end against (3, 0, 0)
    end = sum(1.1 * np.array([math.cos(math.radians(k)), math.sin(math.radians(k))]) for k in range(3))
    assert np.allclose(three.translation, np.hypot(end[0] - 3.0, end[1]), atol=1e-12)


def test_rpe_ignores_the_estimate_world_and_undoes_a_given_scale():
    rng = np.random.default_rng(6)
    gt = random_poses(rng, 30)
    moved = apply_similarity(known_similarity(rng), gt)
    assert relative_pose_error(moved, gt, 2).translation.max() < 1e-9
    halved = gt.copy()
    halved[:, :3, 3] *= 0.5
    assert relative_pose_error(halved, gt, 2).translation.max() > 0.01
    assert relative_pose_error(halved, gt, 2, scale=2.0).translation.max() < 1e-12


def test_rpe_rotation_agrees_with_scipy_and_stays_accurate_for_tiny_angles():
    rng = np.random.default_rng(7)
    gt = random_poses(rng, 20)
    est = np.array([T @ make_transform(matrix_from_rotvec(rng.normal(0, 0.05, 3)), rng.normal(0, 0.01, 3))
                    for T in gt])
    rpe = relative_pose_error(est, gt, 1)
    for (i, j), angle in zip(rpe.pairs, rpe.rotation, strict=True):
        E = np.linalg.inv(np.linalg.inv(gt[i]) @ gt[j]) @ (np.linalg.inv(est[i]) @ est[j])
        assert angle == pytest.approx(Rotation.from_matrix(E[:3, :3]).magnitude(), abs=1e-12)
    tiny = gt @ make_transform(matrix_from_rotvec([3e-9, 0.0, 0.0]), np.zeros(3))
    tiny[::2] = gt[::2]
    assert np.allclose(relative_pose_error(tiny, gt, 1).rotation, 3e-9, rtol=1e-6)


def test_rpe_pairs_over_a_travelled_distance():
    gt = line_poses([0.5, 0.5, 0.25, 0.25, 0.5, 2.0])  # path at rows: 0, 0.5, 1, 1.25, 1.5, 2, 4
    pairs = rpe_pairs(gt, 1.0, "m")
    assert pairs.tolist() == [[0, 2], [1, 4], [2, 5], [3, 6], [4, 6], [5, 6]]
    assert rpe_pairs(gt, 3.0, "m").tolist() == [[0, 6], [1, 6], [2, 6]]  # from 1.25 m on, 3 m is never reached
    assert rpe_pairs(gt, 1e-12, "m").tolist() == [[k, k + 1] for k in range(6)]  # never a row with itself
    assert rpe_pairs(gt, 2, "frames").tolist() == [[k, k + 2] for k in range(5)]
    with pytest.raises(ValueError, match="whole number >= 1, got 1.5"):
        rpe_pairs(gt, 1.5, "frames")
    with pytest.raises(ValueError, match="unknown RPE delta unit 'km'"):
        rpe_pairs(gt, 1, "km")  # type: ignore[arg-type]


def test_associate_takes_the_closest_pairs_first_one_to_one():
    ms = 1_000_000
    a = np.array([0, 5, 100, 200, 400]) * ms
    b = np.array([203, 3, 96, 290]) * ms  # any order
    assert associate(a, b, 20 * ms).tolist() == [[1, 1], [2, 2], [3, 0]]  # 5 -> 3 beats 0 -> 3
    assert associate(a, b, 0).tolist() == []
    # 0 ms and 5 ms both want 3 ms: the closer takes it, and 0 ms falls back on its next free neighbour in reach
    assert associate(a, b, 100 * ms).tolist() == [[1, 1], [2, 2], [3, 0]]
    assert associate(np.array([0, 5]) * ms, np.array([3, -40]) * ms, 50 * ms).tolist() == [[0, 1], [1, 0]]


def brute_force_association(a: np.ndarray, b: np.ndarray, max_dt: int) -> list[list[int]]:
    """TUM's rule spelled out over every pair: closest first, each stamp used once."""
    candidates = sorted((abs(int(x) - int(y)), i, j) for i, x in enumerate(a) for j, y in enumerate(b)
                        if abs(int(x) - int(y)) <= max_dt)
    used_a, used_b, pairs = set(), set(), []
    for _, i, j in candidates:
        if i not in used_a and j not in used_b:
            used_a.add(i)
            used_b.add(j)
            pairs.append([i, j])
    return sorted(pairs)


@pytest.mark.parametrize("seed", range(5))
def test_associate_matches_the_rule_spelled_out_over_every_pair(seed):
    rng = np.random.default_rng(seed)
    a = rng.integers(0, 10_000, 60)
    b = np.concatenate([a[:30] + rng.integers(-300, 300, 30), rng.integers(0, 10_000, 50)])
    rng.shuffle(b)
    for max_dt in (0, 50, 400, 20_000):
        assert associate(a, b, max_dt).tolist() == brute_force_association(a, b, max_dt)


def test_associate_refuses_stamps_that_are_not_int_nanoseconds():
    with pytest.raises(ValueError, match="stamps must be int nanoseconds, got float64"):
        associate(np.array([0.5]), np.array([1]), 10)
    with pytest.raises(ValueError, match=r"stamps_b must have shape \(M,\), got \(1, 1\)"):
        associate(np.array([1]), np.array([[1]]), 10)
    with pytest.raises(ValueError, match="max_dt_ns must be >= 0"):
        associate(np.array([1]), np.array([1]), -1)


def test_score_reports_ate_and_rpe_with_the_sim3_scale_applied():
    gt = line_poses([1.0] * 8, yaw_per_step=0.2)
    est = apply_similarity(Similarity(np.eye(3), np.array([5.0, 0, 0]), 0.5), gt)
    score = score_trajectory(est, gt, "sim3", 2)
    figures = score.to_dict()
    assert figures["matched"] == 9 and figures["scale"] == pytest.approx(2.0)
    assert figures["ate_m"]["max"] < 1e-9 and figures["rpe"]["translation_m"]["max"] < 1e-9
    assert figures["rpe"]["pairs"] == 7
    assert score_trajectory(est, gt, "se3", 2).rpe.translation_stats.max > 0.4


def test_error_stats_of_nothing_are_nan_with_a_zero_count():
    stats = error_stats(np.array([]))
    assert stats.count == 0 and math.isnan(stats.rmse)
