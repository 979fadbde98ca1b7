"""Bundle adjustment and pose-only refinement (services.slam.optimisation) on synthetic problems.

Problems (tests.slam_problems): keyframes on a 2 m arc looking at points 5 to 9 m away, 1 px noise
(times each observation's sigma), 10 % of observations replaced by random pixels, a start 1 deg and
5 cm off for free poses and 5 cm per axis for points. The scipy reference (tests.slam_reference)
minimises the same cost independently.
"""

import dataclasses

import numpy as np
import pytest

from services.geometry.camera import project_points
from services.geometry.rotation import rotation_angle
from services.geometry.se3 import invert, make_transform, transform_points
from services.slam.optimisation import CHI2_2DOF_95, BundleProblem, bundle_adjust, refine_pose
from tests.slam_problems import keyframe_poses, pose_problem, synthetic_problem
from tests.slam_reference import reference_bundle_adjust, reference_refine_pose, robust_cost


def pose_errors(poses: dict[int, np.ndarray], truth: dict[int, np.ndarray]) -> tuple[float, float]:
    """Largest rotation (deg) and camera-centre (m) difference over the keyframes of ``truth``."""
    angles = [np.degrees(rotation_angle(poses[k][:3, :3], T[:3, :3])) for k, T in truth.items()]
    centres = [np.linalg.norm(invert(poses[k])[:3, 3] - invert(T)[:3, 3]) for k, T in truth.items()]
    return max(angles), max(centres)


@pytest.mark.parametrize("levels", [0, 4])
def test_matches_scipy_reference(levels):
    """pycolmap and scipy reach the same cost and the same poses; with pyramid sigmas too (whitening)."""
    sp = synthetic_problem(np.random.default_rng(10 + levels), keyframes=10, points=300, levels=levels, fixed=(0, 9))
    reference = reference_bundle_adjust(sp.problem, tolerance=1e-10)
    result = bundle_adjust(sp.problem, max_iterations=500, tolerance=0.0)
    cost = robust_cost(sp.problem, result.poses, result.points)
    assert cost == pytest.approx(reference.cost, rel=1e-6)
    assert cost <= reference.cost * (1 + 1e-8)
    angle, distance = pose_errors(result.poses, reference.poses)
    assert angle < 0.01 and distance < 1e-3
    start_angle, _ = pose_errors(sp.problem.poses, reference.poses)
    assert start_angle > 0.5


@pytest.mark.parametrize("levels", [0, 4])
def test_error_falls_to_noise_and_outliers_are_flagged(levels):
    sp = synthetic_problem(np.random.default_rng(20 + levels), keyframes=15, points=1000, levels=levels)
    problem = sp.problem
    result = bundle_adjust(problem)
    sigmas = np.ones(len(problem.pixels)) if problem.sigmas is None else problem.sigmas
    assert result.initial_rms_px > 5.0
    whitened = result.errors_px[~result.outliers] / sigmas[~result.outliers]
    # chi2(2) cut at 5.991 leaves an RMS of 1.30 px per unit sigma; the fit absorbs a little more
    assert 1.0 < np.sqrt(np.mean(whitened ** 2)) < 1.35
    assert result.outliers[sp.gross].all()
    clean = ~sp.gross
    assert result.outliers[clean].mean() < 0.08
    assert np.array_equal(result.outliers, ~((result.errors_px / sigmas) ** 2 <= CHI2_2DOF_95))
    angle, distance = pose_errors(result.poses, sp.poses)
    assert angle < 0.2 and distance < 0.02
    assert 1 <= result.iterations <= 20 and result.seconds > 0


def test_fixed_poses_do_not_move_and_lonely_points_stay():
    """Fixed poses stay bit for bit; points seen once are left as given, and one behind its only
    keyframe is an outlier with an infinite error."""
    sp = synthetic_problem(np.random.default_rng(3), keyframes=10, points=500, fixed=(0, 4, 9))
    problem = sp.problem
    ids, counts = np.unique(problem.point_ids, return_counts=True)
    lonely = ids[counts == 1]
    ahead, behind = max(problem.points) + 1, max(problem.points) + 2
    behind_world = transform_points(invert(problem.poses[4]), np.array([0.0, 0.0, -3.0]))[0]
    problem = dataclasses.replace(
        problem, points={**problem.points, ahead: np.array([0.0, 0.0, 7.0]), behind: behind_world},
        frame_ids=np.r_[problem.frame_ids, 5, 4], point_ids=np.r_[problem.point_ids, ahead, behind],
        pixels=np.vstack([problem.pixels, [[100.0, 100.0], [320.0, 240.0]]]))
    result = bundle_adjust(problem)
    for k in (0, 4, 9):
        assert np.array_equal(result.poses[k], problem.poses[k])
    assert pose_errors(result.poses, {k: problem.poses[k] for k in (2, 7)})[0] > 0.1
    for point in [*lonely.tolist(), ahead, behind]:
        assert np.array_equal(result.points[point], problem.points[point])
    assert result.errors_px[-1] == np.inf and result.outliers[-1]
    assert np.isfinite(result.errors_px[-2])


def test_exact_data_recovers_the_truth():
    """No noise, no outliers, pyramid sigmas: the solve lands on the truth (the whitening is exact)."""
    sp = synthetic_problem(np.random.default_rng(4), keyframes=10, points=500, noise_px=0.0, gross_fraction=0.0,
                           levels=4)
    result = bundle_adjust(sp.problem, max_iterations=100, tolerance=0.0)
    angle, distance = pose_errors(result.poses, sp.poses)
    assert angle < 1e-5 and distance < 1e-7
    assert result.final_rms_px < 1e-6 and not result.outliers.any()


@pytest.mark.parametrize("levels", [0, 4])
def test_fix_scale_with_one_fixed_keyframe(levels):
    """One fixed keyframe and ``fix_scale``: exact data is recovered up to one scale about that keyframe."""
    sp = synthetic_problem(np.random.default_rng(5), keyframes=8, points=500, noise_px=0.0, gross_fraction=0.0,
                           fixed=(0,), levels=levels)
    result = bundle_adjust(sp.problem, max_iterations=100, tolerance=0.0, fix_scale=True)
    origin = invert(sp.poses[0])[:3, 3]
    true = np.stack([invert(sp.poses[k])[:3, 3] - origin for k in sorted(sp.poses)])
    found = np.stack([invert(result.poses[k])[:3, 3] - origin for k in sorted(sp.poses)])
    scale = float(np.sum(found * true) / np.sum(true * true))
    assert 0.8 < scale < 1.2
    assert np.abs(found - scale * true).max() < 1e-6
    assert result.final_rms_px < 1e-6


def centres_from(poses: dict[int, np.ndarray], origin_id: int) -> np.ndarray:
    """(F, 3) camera centres of ``poses`` by id, less the centre of keyframe ``origin_id``."""
    origin = invert(poses[origin_id])[:3, 3]
    return np.stack([invert(poses[k])[:3, 3] - origin for k in sorted(poses)])


def test_fix_scale_keeps_the_window_scale_when_a_keyframe_sits_next_to_the_fixed_one():
    """The map's second keyframe lies 5 mm from the fixed first one and starts 5 cm off, as after a
    short-baseline initialisation: the solve keeps the window's scale (the free keyframes as far from
    the fixed one, in sum, as at the start), not one read off that keyframe's poorly known offset."""
    truth = keyframe_poses(8)
    truth[1] = invert(invert(truth[0]) @ make_transform(np.eye(3), np.array([0.005, 0.0, 0.0])))
    sp = synthetic_problem(np.random.default_rng(6), points=500, gross_fraction=0.0, fixed=(0,), poses=truth)
    result = bundle_adjust(sp.problem, max_iterations=100, fix_scale=True)
    start, found, true = (centres_from(poses, 0) for poses in (sp.problem.poses, result.poses, sp.poses))
    assert np.linalg.norm(found, axis=1).sum() == pytest.approx(np.linalg.norm(start, axis=1).sum(), rel=1e-9)
    scale = float(np.sum(found * true) / np.sum(true * true))
    assert scale == pytest.approx(np.linalg.norm(start, axis=1).sum() / np.linalg.norm(true, axis=1).sum(), rel=0.01)
    assert np.abs(found[2:] - scale * true[2:]).max() < 0.02
    assert result.final_rms_px < 1.2


def broken(problem: BundleProblem, name: str) -> BundleProblem:
    """``problem`` with one thing wrong."""
    m = len(problem.pixels)
    changes = {
        "K": {"K": np.eye(4)},
        "skew": {"K": problem.K + np.array([[0, 1.0, 0], [0, 0, 0], [0, 0, 0]])},
        "pixels": {"pixels": problem.pixels[:, :1]},
        "nan": {"pixels": np.where(np.arange(m)[:, None] == 3, np.nan, problem.pixels)},
        "frame_ids": {"frame_ids": problem.frame_ids[:-1]},
        "float_ids": {"point_ids": problem.point_ids.astype(float)},
        "sigmas": {"sigmas": -np.ones(m)},
        "pose": {"poses": {**problem.poses, 2: 2 * problem.poses[2]}},
        "point": {"points": {**problem.points, 0: np.zeros(2)}},
        "unknown_frame": {"frame_ids": np.where(np.arange(m) == 0, 99, problem.frame_ids)},
        "unknown_point": {"point_ids": np.where(np.arange(m) == 0, 10 ** 6, problem.point_ids)},
        "unknown_fixed": {"fixed": frozenset({0, 99})},
        "all_fixed": {"fixed": frozenset(problem.poses)},
        "none_fixed": {"fixed": frozenset()},
    }
    return dataclasses.replace(problem, **changes[name])


@pytest.mark.parametrize(("name", "message"), [
    ("K", "K must have shape"), ("skew", "zero-skew"), ("pixels", "pixels must have shape"),
    ("nan", "pixels must be finite"), ("frame_ids", "frame_ids must have shape"), ("float_ids", "point_ids must be"),
    ("sigmas", "sigmas must be"),
    ("pose", r"poses\[2\]"), ("point", r"points\[0\]"), ("unknown_frame", "frame_ids names ids with no pose: \\[99\\]"),
    ("unknown_point", "point_ids names ids with no point"), ("unknown_fixed", "fixed names ids with no pose"),
    ("all_fixed", "no free pose"), ("none_fixed", "no observed keyframe is fixed"),
])
def test_bad_problems_raise_one_clear_error(name, message):
    sp = synthetic_problem(np.random.default_rng(6), keyframes=4, points=100)
    with pytest.raises(ValueError, match=message):
        bundle_adjust(broken(sp.problem, name))


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_refine_pose_recovers_a_perturbed_pose_and_flags_outliers(seed):
    K, T, points, pixels, sigmas, gross, start = pose_problem(seed)
    result = refine_pose(K, start, points, pixels, sigmas)
    angle, distance = pose_errors({0: result.T_camera_world}, {0: T})
    assert angle < 0.1 and distance < 0.02
    assert not result.inliers[gross].any()
    assert result.inliers[~gross].mean() > 0.92
    projected = project_points(transform_points(result.T_camera_world, points), K)
    whitened = np.linalg.norm(pixels - projected, axis=1) / sigmas
    assert np.array_equal(result.inliers, whitened ** 2 <= CHI2_2DOF_95)
    assert 0.8 < result.rms_px < 2.0


def test_refine_pose_leaves_out_points_behind_the_camera():
    K, T, points, pixels, sigmas, gross, start = pose_problem(6, count=300)
    behind = transform_points(invert(T), np.array([[0.0, 0.0, -3.0], [1.0, 0.5, -6.0]]))
    result = refine_pose(K, start, np.vstack([points, behind]), np.vstack([pixels, [[320.0, 240.0], [10.0, 20.0]]]),
                         np.r_[sigmas, 1.0, 1.0])
    assert not result.inliers[-2:].any()
    angle, distance = pose_errors({0: result.T_camera_world}, {0: T})
    assert angle < 0.2 and distance < 0.03


def test_refine_pose_one_round_matches_scipy():
    """One round on every observation minimises the same robust cost as scipy's least_squares."""
    K, T, points, pixels, sigmas, _, start = pose_problem(4, count=400)
    result = refine_pose(K, start, points, pixels, sigmas, rounds=1, max_iterations=50)
    reference = reference_refine_pose(K, start, points, pixels, sigmas)
    angle, distance = pose_errors({0: result.T_camera_world}, {0: reference})
    assert angle < 1e-4 and distance < 1e-5


@pytest.mark.parametrize(("change", "message"), [
    ({"points_world": np.zeros((5, 2))}, "points_world must have shape"),
    ({"pixels": np.zeros((3, 2))}, "pixels must have shape"), ({"sigmas": np.zeros(1000)}, "sigmas must be"),
    ({"T_camera_world": np.eye(3)}, "T_camera_world must have shape"),
    ({"K": np.ones((3, 3))}, "zero-skew pinhole"),
])
def test_refine_pose_bad_input_raises(change, message):
    K, _, points, pixels, sigmas, _, start = pose_problem(5)
    arguments = {"K": K, "T_camera_world": start, "points_world": points, "pixels": pixels, "sigmas": sigmas}
    with pytest.raises(ValueError, match=message):
        refine_pose(**{**arguments, **change})
