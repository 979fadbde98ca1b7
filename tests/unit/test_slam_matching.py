"""Descriptor matching and search by projection for SLAM, against OpenCV where it does the same."""

import cv2
import numpy as np

from services.slam.map.map_point import PointArrays
from services.slam.matching import (
    hamming,
    hamming_matrix,
    match_candidates,
    match_descriptors,
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
