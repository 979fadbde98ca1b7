"""Loop closing's parts: place recognition finds a revisit, Sim(3) from noisy matches with outliers, and a
pose graph that spreads a loop's error over it."""

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from services.geometry.se3 import transform_points
from services.slam.loop.places import PlaceIndex, words
from services.slam.loop.pose_graph import edge_residuals, optimise_pose_graph
from services.slam.loop.sim3 import decompose, fit_sim3, similarity


def _noisy(descriptors: np.ndarray, rng: np.random.Generator, flips: int) -> np.ndarray:
    """``descriptors`` (N, 32) with ``flips`` random bits of each flipped."""
    bits = np.unpackbits(descriptors, axis=1)
    for row in bits:
        row[rng.choice(256, flips, replace=False)] ^= 1
    return np.packbits(bits, axis=1)


def test_words_are_distinct_sorted_and_shared_by_near_descriptors():
    rng = np.random.default_rng(1)
    descriptors = rng.integers(0, 256, (200, 32), dtype=np.uint8)
    found = words(descriptors)
    assert np.all(np.diff(found) > 0)
    near = np.intersect1d(found, words(_noisy(descriptors, rng, 10))).size
    far = np.intersect1d(found, words(rng.integers(0, 256, (200, 32), dtype=np.uint8))).size
    assert near > 100 * max(far, 1) / 10 and far < 5


def test_place_recognition_finds_the_true_revisit_among_keyframes():
    """Twelve places along a path, each seen by two consecutive keyframes (covisible neighbours); the
    last keyframe sees place 0 again with 25 bits of each descriptor changed: the candidate is keyframe 0
    or 1, never a neighbour; a frame of another place scores a tenth of the revisit's at most."""
    rng = np.random.default_rng(2)
    places = [rng.integers(0, 256, (600, 32), dtype=np.uint8) for _ in range(12)]
    index = PlaceIndex()
    keyframes = {}
    for k in range(24):
        place = places[k // 2]
        keyframes[k] = _noisy(place, rng, 12)
        index.add(k, keyframes[k])
    revisit = _noisy(places[0], rng, 25)
    neighbours = {23, 22}

    def group(k: int) -> set[int]:
        return {k - 1, k + 1} - {-1, 24}

    candidates = index.loop_candidates(24, revisit, neighbours, group)
    assert candidates and candidates[0] in (0, 1)
    assert not set(candidates) & neighbours
    assert set(candidates) <= {0, 1, 2}
    elsewhere = index.scores(rng.integers(0, 256, (600, 32), dtype=np.uint8))
    assert max(elsewhere.values(), default=0.0) < index.scores(revisit)[0] / 10


def test_sim3_recovers_a_known_similarity_from_noisy_matches_with_outliers():
    rng = np.random.default_rng(3)
    R = Rotation.random(random_state=4).as_matrix()
    S_true = similarity(1.7, R, np.array([0.4, -1.2, 2.0]))
    source = rng.uniform(-2, 2, (300, 3))
    target = transform_points(S_true, source) + rng.normal(0, 0.01, (300, 3))
    outliers = rng.random(300) < 0.4
    target[outliers] = rng.uniform(-5, 5, (int(outliers.sum()), 3))
    fit = fit_sim3(source, target, threshold=0.05**2)
    assert fit is not None
    assert np.array_equal(fit.inliers, ~outliers)
    scale, R_fit, t_fit = decompose(fit.S_target_source)
    assert scale == pytest.approx(1.7, rel=2e-3)
    assert np.degrees(Rotation.from_matrix(R_fit @ R.T).magnitude()) < 0.2
    assert np.linalg.norm(t_fit - S_true[:3, 3]) < 0.01
    reference, reference_scale = cv2.estimateAffine3D(source[fit.inliers], target[fit.inliers], force_rotation=True)
    assert reference_scale == pytest.approx(scale, rel=1e-9)
    np.testing.assert_allclose(reference[:, :3], R_fit, atol=1e-9)
    np.testing.assert_allclose(reference[:, 3], t_fit, atol=1e-9)


def test_sim3_refuses_too_few_inliers():
    rng = np.random.default_rng(5)
    assert fit_sim3(rng.normal(size=(2, 3)), rng.normal(size=(2, 3)), 0.01) is None
    assert fit_sim3(rng.normal(size=(50, 3)), rng.normal(size=(50, 3)), 1e-6, min_inliers=10) is None


def _circle(count: int) -> list[np.ndarray]:
    """``count`` camera poses ``S_camera_world`` round a circle of radius 2, looking outwards."""
    poses = []
    for k in range(count):
        angle = 2 * np.pi * k / count
        R_world_camera = Rotation.from_euler("z", angle).as_matrix()
        centre = 2 * np.array([np.cos(angle), np.sin(angle), 0.0])
        poses.append(np.linalg.inv(similarity(1.0, R_world_camera, centre)))
    return poses


def test_pose_graph_distributes_a_known_loop_error():
    """Odometry over 40 poses round a circle, each step's scale 1 % short and turned 0.3 deg too far:
    integrated, its end is far from its start. One loop edge from the truth and the first node fixed:
    the optimised poses agree with the truth within a fraction of the drift, the error spread along the
    loop (no node worse than a third of the end's drift before)."""
    truth = _circle(40)
    drift = similarity(0.99, Rotation.from_euler("y", 0.3, degrees=True).as_matrix(), np.zeros(3))
    edges = []
    integrated = [truth[0]]
    for k in range(1, 40):
        step = truth[k] @ np.linalg.inv(truth[k - 1])
        noisy = drift @ step
        edges.append((k, k - 1, noisy))
        integrated.append(noisy @ integrated[-1])
    edges.append((0, 39, truth[0] @ np.linalg.inv(truth[39])))
    start = dict(enumerate(integrated))

    def centre_errors(poses: dict[int, np.ndarray]) -> np.ndarray:
        return np.array([np.linalg.norm(np.linalg.inv(poses[k])[:3, 3] - np.linalg.inv(truth[k])[:3, 3])
                         for k in range(40)])

    before = centre_errors(start)
    result = optimise_pose_graph(start, edges, {0})
    after = centre_errors(result.poses)
    print(f"end drift {before[-1]:.3f}, after: max {after.max():.3f}, cost {result.initial_cost:.3g} -> "
          f"{result.final_cost:.3g} in {result.evaluations} evaluations")
    assert before[-1] > 0.3
    assert after.max() < before.max() / 3
    assert result.final_cost < result.initial_cost / 10
    np.testing.assert_allclose(result.poses[0], truth[0])


def test_edge_residuals_vanish_on_consistent_measurements_and_read_the_scale():
    poses = np.array(_circle(4))
    first, second = np.array([1, 2]), np.array([0, 1])
    measured = np.array([poses[1] @ np.linalg.inv(poses[0]), poses[2] @ np.linalg.inv(poses[1])])
    np.testing.assert_allclose(edge_residuals(poses, first, second, np.linalg.inv(measured)), 0, atol=1e-12)
    scaled = measured.copy()
    scaled[0] = similarity(2.0, np.eye(3), np.zeros(3)) @ measured[0]
    residual = edge_residuals(poses, first, second, np.linalg.inv(scaled))
    assert residual[0, 6] == pytest.approx(-np.log(2.0))
