"""Descriptor matching and search by projection for SLAM, against OpenCV where it does the same."""

import itertools

import cv2
import numpy as np
from scipy.spatial import cKDTree

from services.slam.map.map_point import PointArrays
from services.slam.matching import (
    best_two,
    hamming,
    hamming_matrix,
    match_candidates,
    match_descriptors,
    pairs_within,
    rotation_consistent,
    search_by_projection,
)
from services.slam.projection import project_points

RNG = np.random.default_rng(7)


def flip_bits(descriptors: np.ndarray, bits: int, rng: np.random.Generator) -> np.ndarray:
    """Copies of (N, 32) descriptors with ``bits`` random bits of each flipped."""
    unpacked = np.unpackbits(descriptors, axis=1)
    for row in unpacked:
        row[rng.choice(256, bits, replace=False)] ^= 1
    return np.packbits(unpacked, axis=1)


def test_hamming_agrees_with_opencv():
    a = RNG.integers(0, 256, (30, 32), dtype=np.uint8)
    b = RNG.integers(0, 256, (20, 32), dtype=np.uint8)
    expected = np.array([[cv2.norm(x, y, cv2.NORM_HAMMING) for y in b] for x in a])
    np.testing.assert_array_equal(hamming_matrix(a, b), expected)
    np.testing.assert_array_equal(hamming(a[:20], b), np.diag(expected[:20]))


def test_descriptor_matches_pass_distance_and_ratio_tests():
    a = RNG.integers(0, 256, (200, 32), dtype=np.uint8)
    order = RNG.permutation(200)
    b = flip_bits(a[order], 20, RNG)
    rows, columns = match_descriptors(a, b, max_distance=64, ratio=0.8)
    assert len(rows) == 200
    np.testing.assert_array_equal(order[columns], rows)
    assert len(match_descriptors(a, b, max_distance=10, ratio=0.8)[0]) == 0
    # a duplicate of a's row 0 in b makes row 0 ambiguous: the ratio test drops it
    ambiguous = np.vstack([b, b[np.flatnonzero(order == 0)]])
    rows, _ = match_descriptors(a, ambiguous, max_distance=64, ratio=0.8)
    assert 0 not in rows and len(rows) == 199


def test_candidate_matches_agree_with_opencvs_masked_matcher():
    """Among candidate pairs only, the same matches as OpenCV's brute force with a mask, then the same tests."""
    a = RNG.integers(0, 256, (300, 32), dtype=np.uint8)
    order = RNG.permutation(300)
    b = flip_bits(a[order], 30, RNG)
    mask = (RNG.random((300, 300)) < 0.1).astype(np.uint8)
    mask[order, np.arange(300)] = RNG.random(300) < 0.7
    rows, columns = np.nonzero(mask)
    found = match_candidates(a, b, rows, columns, max_distance=64, ratio=0.8)
    expected = []
    for m in cv2.BFMatcher(cv2.NORM_HAMMING).knnMatch(a, b, k=2, mask=mask):
        second = m[1].distance if len(m) == 2 else np.inf
        if len(m) and m[0].distance <= 64 and m[0].distance < 0.8 * second:
            expected.append((m[0].queryIdx, m[0].trainIdx))
    assert 150 < len(expected) < 300
    assert sorted(zip(*(f.tolist() for f in found), strict=True)) == sorted(expected)
    assert np.all(order[found[1]] == found[0])


def test_search_by_projection_keeps_window_level_and_uniqueness():
    keypoints = np.array([[100.0, 100.0], [105.0, 100.0], [300.0, 300.0], [310.0, 300.0]])
    levels = np.array([0, 0, 3, 0])
    descriptors = RNG.integers(0, 256, (4, 32), dtype=np.uint8)
    points = flip_bits(descriptors[[0, 2, 3, 3]], 10, RNG)
    predicted = np.array([[102.0, 101.0], [301.0, 300.0], [309.0, 301.0], [309.0, 299.0]])
    rows, matched = search_by_projection(predicted, np.full(4, 8.0), np.array([0, 3, 0, 0]), points, keypoints, levels,
                                         descriptors, np.ones(4, bool), max_distance=50, ratio=0.9)
    # points 2 and 3 both claim keypoint 3: the closer descriptor keeps it
    assert dict(zip(rows.tolist(), matched.tolist(), strict=True)).items() >= {(0, 0), (1, 2)}
    assert len(set(matched.tolist())) == len(matched) == 3
    # keypoint 2 is on level 3: a point predicted on level 0 does not reach it
    rows, matched = search_by_projection(predicted[1:2], np.full(1, 8.0), np.array([0]), points[1:2], keypoints, levels,
                                         descriptors, np.ones(4, bool), max_distance=50, ratio=0.9)
    assert len(rows) == 0
    # taken keypoints and narrow windows are not searched
    available = np.array([False, True, True, True])
    rows, matched = search_by_projection(predicted[:1], np.full(1, 8.0), np.zeros(1, np.int64), points[:1], keypoints,
                                         levels, descriptors, available, max_distance=50, ratio=0.9)
    assert 0 not in matched
    rows, _ = search_by_projection(predicted[:1], np.full(1, 1.0), np.zeros(1, np.int64), points[:1], keypoints, levels,
                                   descriptors, np.ones(4, bool), max_distance=50, ratio=0.9)
    assert len(rows) == 0


def test_best_two_is_the_plain_loop_for_integer_and_float_costs():
    groups = RNG.integers(0, 300, 5000)
    for costs in (RNG.integers(0, 257, 5000).astype(np.int32), RNG.integers(0, 257, 5000).astype(np.float64)):
        rows, best, second = best_two(groups, costs)
        expected = {}
        for index, (group, cost) in enumerate(zip(groups.tolist(), costs.tolist(), strict=True)):
            pairs = expected.setdefault(group, [])
            pairs.append((cost, index))
        for row, lowest, runner_up in zip(rows.tolist(), best.tolist(), second.tolist(), strict=True):
            ranked = sorted(expected.pop(int(groups[row])))
            assert (lowest, row) == (ranked[0][0], ranked[0][1])
            assert runner_up == (ranked[1][0] if len(ranked) > 1 else np.inf)
        assert not expected


def _kd_tree_pairs(centres: np.ndarray, radii: np.ndarray, pixels: np.ndarray) -> set[tuple[int, int]]:
    """The pairs within each radius as SciPy's k-d tree finds them (the reference)."""
    found = cKDTree(pixels).query_ball_point(centres, radii)
    return {(row, int(column)) for row, columns in enumerate(found) for column in columns}


def test_pairs_within_are_the_kd_tree_pairs():
    pixels = RNG.uniform(-5, 645, (1500, 2))
    for radii in (np.full(400, 100.0), 4.0 * 1.2 ** RNG.integers(0, 8, 400), np.full(400, 0.5)):
        centres = RNG.uniform(-20, 660, (400, 2))
        rows, columns = pairs_within(centres, radii, pixels)
        assert set(zip(rows.tolist(), columns.tolist(), strict=True)) == _kd_tree_pairs(centres, radii, pixels)
    grid = np.array(list(itertools.product(range(0, 40), range(0, 30))), np.float64)  # distances exactly 5 (3-4-5)
    centres, radii = np.array([[10.0, 10.0], [20.0, 20.0]]), np.array([5.0, 3.0])
    rows, columns = pairs_within(centres, radii, grid)
    found = set(zip(rows.tolist(), columns.tolist(), strict=True))
    assert found == _kd_tree_pairs(centres, radii, grid)
    assert (0, int(np.flatnonzero((grid == [13.0, 14.0]).all(axis=1))[0])) in found  # exactly on the circle
    rows, _ = pairs_within(np.array([[np.nan, 1.0]]), np.array([5.0]), grid)
    assert len(rows) == 0


def test_search_by_projection_is_the_kd_tree_search_on_real_features():
    """The grid's candidates give the matches the k-d tree's gave, on two frames of the room."""
    from services.slam.features import FeatureExtractor
    from services.slam.settings import SlamSettings
    from services.synthetic import make_scene

    scene = make_scene("room")
    s = SlamSettings()
    extractor = FeatureExtractor(scene.cameras[0], s.max_keypoints, s.levels, s.scale_factor, s.fast_threshold)
    a, b = (extractor.extract(scene.render(i).images["cam0"]) for i in (0, 2))
    available = RNG.random(len(b)) < 0.8
    for radii in (np.full(len(a), 100.0), 15.0 * 1.2 ** a.levels.astype(np.float64),
                  4.0 * 1.2 ** a.levels.astype(np.float64)):
        found = search_by_projection(a.pixels, radii, a.levels, a.descriptors, b.pixels, b.levels, b.descriptors,
                                     available, 64, 0.9)
        free = np.flatnonzero(available)
        pairs = sorted(_kd_tree_pairs(a.pixels, radii, b.pixels[free]))
        rows = np.array([r for r, _ in pairs], np.int64)
        columns = free[np.array([c for _, c in pairs], np.int64)]
        near = np.abs(b.levels[columns] - a.levels[rows]) <= 1
        expected = match_candidates(a.descriptors, b.descriptors, rows[near], columns[near], 64, 0.9)
        assert len(expected[0]) > 10
        assert np.array_equal(found[0], expected[0]) and np.array_equal(found[1], expected[1])


def test_rotation_consistency_drops_odd_turns():
    turns = np.r_[np.full(50, 10.0), np.full(30, 14.0), [180.0, 250.0]]
    angles = RNG.uniform(0, 360, len(turns))
    kept = rotation_consistent(angles, np.mod(angles + turns, 360.0))
    assert kept[:80].all() and not kept[80:].any()


def test_projection_agrees_with_opencv_and_predicts_levels():
    positions = RNG.uniform([-2, -1.5, 1], [2, 1.5, 8], (300, 3))
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(np.array([0.05, -0.1, 0.02]))[0]
    T[:3, 3] = [0.1, 0.0, 0.3]
    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    centre = -T[:3, :3].T @ T[:3, 3]
    distances = np.linalg.norm(positions - centre, axis=1)
    normals = (positions - centre) / distances[:, None]
    points = PointArrays(np.arange(300), positions, np.zeros((300, 32), np.uint8), normals, np.full(300, 0.5),
                         np.full(300, 4.0))
    projected = project_points(points, T, K, (640, 480), 1.2, 8)
    expected = cv2.projectPoints(positions, cv2.Rodrigues(T[:3, :3])[0], T[:3, 3], K, None)[0].reshape(-1, 2)
    inside = np.all((expected >= 0) & (expected <= [639, 479]), axis=1) & (distances >= 0.4) & (distances <= 4.8)
    np.testing.assert_array_equal(projected.rows, np.flatnonzero(inside))
    np.testing.assert_allclose(projected.pixels, expected[inside], atol=1e-9)
    levels = np.clip(np.ceil(np.log(4.0 / distances[inside]) / np.log(1.2)), 0, 7)
    np.testing.assert_array_equal(projected.levels, levels)
