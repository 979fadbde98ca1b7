"""The SLAM map: observations, covisibility, local map queries, point culling and fusion."""

import cv2
import numpy as np
import pytest

from services.slam.features import FrameFeatures
from services.slam.map import database, point_summary
from services.slam.map.cleaner import LocalMapCleaner
from services.slam.map.covisibility import CovisibilityGraph
from services.slam.map.database import MapDatabase
from services.slam.settings import SlamSettings


def features(n: int, seed: int = 0) -> FrameFeatures:
    rng = np.random.default_rng(seed)
    return FrameFeatures(pixels=rng.uniform(0, 400, (n, 2)), levels=np.zeros(n, np.int64),
                         angles=np.zeros(n, np.float32), descriptors=rng.integers(0, 256, (n, 32), dtype=np.uint8),
                         sigmas=np.ones(n))


def pose(x: float) -> np.ndarray:
    T = np.eye(4)
    T[0, 3] = -x
    return T


@pytest.fixture
def chain() -> MapDatabase:
    """Keyframes 0, 1, 2 along x; points 0-9 seen by 0 and 1, points 10-14 by 1 and 2, point 15 by all."""
    slam_map = MapDatabase(1.2, 8)
    for k in range(3):
        slam_map.add_keyframe(k, pose(0.1 * k), features(20, k), np.full(20, -1))
    for i in range(10):
        slam_map.add_point(np.array([i * 0.1, 0.0, 2.0]), {0: i, 1: i})
    for i in range(10, 15):
        slam_map.add_point(np.array([i * 0.1, 0.0, 2.0]), {1: i, 2: i})
    slam_map.add_point(np.array([0.0, 0.5, 2.0]), {0: 15, 1: 15, 2: 15})
    return slam_map


def test_covisibility_counts_shared_points(chain):
    graph = CovisibilityGraph(chain)
    assert graph.covisibility(1) == {0: 11, 2: 6}
    assert graph.covisibility(0) == {1: 11, 2: 1}
    assert graph.covisible(0, 5, least=2) == [1]
    assert chain.keyframes[0].point_ids[:10].tolist() == list(range(10))


def test_local_map_of_matched_points(chain):
    graph = CovisibilityGraph(chain)
    assert graph.local_keyframes(np.array([10, 11]), 5) == [1, 2, 0]
    assert graph.local_keyframes(np.array([10, 11]), 1) == [1]
    assert chain.points_of([2]).tolist() == [10, 11, 12, 13, 14, 15]
    arrays = chain.arrays(np.array([3, 99, 4]))
    assert arrays.ids.tolist() == [3, 4]
    np.testing.assert_allclose(arrays.positions[:, 0], [0.3, 0.4])


def test_point_descriptor_viewing_direction_and_distances(chain):
    point = chain.points[15]
    descriptors = [chain.keyframes[k].features.descriptors[15] for k in range(3)]
    assert any(np.array_equal(point.descriptor, d) for d in descriptors)
    assert point.normal[2] > 0.9 and np.isclose(np.linalg.norm(point.normal), 1)
    distance = np.linalg.norm(point.position - chain.keyframes[0].centre)
    assert point.max_distance == pytest.approx(distance)
    assert point.min_distance == pytest.approx(distance / 1.2**7)


def test_removing_an_observation_drops_a_point_left_with_one(chain):
    chain.remove_observation(0, 0)
    assert 0 not in chain.points
    assert chain.keyframes[1].point_ids[0] == -1
    chain.remove_observation(15, 2)
    assert chain.points[15].observations == {0: 15, 1: 15}


def test_covisibility_follows_the_database_revision(chain):
    graph = CovisibilityGraph(chain)
    assert graph.covisibility(0) == {1: 11, 2: 1}
    chain.remove_point(15)
    assert graph.covisibility(0) == {1: 10}


def test_culling_removes_recent_points_rarely_found_or_seen(chain):
    cleaner = LocalMapCleaner(chain, SlamSettings(cull_found_ratio=0.25, cull_min_observations=3))
    chain.count_visible(np.arange(5), found=np.zeros(5, bool))
    for _ in range(4):
        chain.count_visible(np.array([0, 1]))
    # points 0 and 1: found 1 of 6 times; 2-4: 1 of 2; 0-9 made in keyframe 0, 10-14 in keyframe 1
    assert cleaner.cull_points(1) == 2
    assert 0 not in chain.points and 1 not in chain.points and 2 in chain.points
    # two keyframes on, points seen by two keyframes only go
    assert cleaner.cull_points(2) == 8
    assert sorted(chain.points) == [10, 11, 12, 13, 14, 15]
    # past probation (three keyframes) nothing is culled
    assert cleaner.cull_points(5) == 0


def test_merging_moves_observations(chain):
    chain.merge_points(15, 12)
    assert 12 not in chain.points
    assert chain.points[15].observations == {0: 15, 1: 15, 2: 15}
    chain.merge_points(10, 0)
    assert chain.points[10].observations == {0: 0, 1: 10, 2: 10}
    assert chain.keyframes[0].point_ids[0] == 10 and chain.keyframes[1].point_ids[0] == -1


def test_revision_grows_on_every_change(chain):
    before = chain.revision
    chain.set_position(3, np.zeros(3))
    chain.set_pose(2, pose(0.3))
    assert chain.revision == before + 2
    np.testing.assert_allclose(chain.keyframes[2].centre, [0.3, 0, 0])


def test_median_descriptors_agree_with_opencv_hamming():
    """Each point's descriptor has the least median Hamming distance (OpenCV's) to its others."""
    rng = np.random.default_rng(3)
    counts = np.array([1, 2, 3, 4, 5, 3, 6, 2])
    descriptors = rng.integers(0, 256, (int(counts.sum()), 32), dtype=np.uint8)
    chosen = point_summary.median_descriptors(descriptors, counts)
    for row, start in enumerate(np.concatenate([[0], np.cumsum(counts)[:-1]])):
        own = descriptors[start:start + counts[row]]
        if len(own) <= 2:
            np.testing.assert_array_equal(chosen[row], own[0])
            continue
        distances = np.array([[cv2.norm(a, b, cv2.NORM_HAMMING) for b in own] for a in own])
        medians = np.sort(distances, axis=1)[:, (len(own) - 1) // 2]
        np.testing.assert_array_equal(chosen[row], own[int(np.argmin(medians))])


def test_refreshing_many_points_equals_updating_each(chain):
    chain.add_observation(3, 2, 3)
    chain.set_pose(2, pose(0.4))
    for point_id in (3, 15):
        chain.set_position(point_id, chain.points[point_id].position + [0.05, -0.1, 0.3])
    one_by_one = {}
    for point_id in sorted(chain.points):
        chain.update_point(point_id)
        point = chain.points[point_id]
        one_by_one[point_id] = (point.descriptor, point.normal, point.min_distance, point.max_distance)
        point.normal, point.max_distance = np.zeros(3), np.inf
    chain.refresh_points(np.array(sorted(chain.points) + [99]))
    for point_id, (descriptor, normal, min_distance, max_distance) in one_by_one.items():
        point = chain.points[point_id]
        np.testing.assert_array_equal(point.descriptor, descriptor)
        np.testing.assert_allclose(point.normal, normal, atol=1e-12)
        assert (point.min_distance, point.max_distance) == pytest.approx((min_distance, max_distance))


def test_refresh_leaves_alone_points_changed_while_it_computed(chain, monkeypatch):
    """What another thread changes between the snapshot and the write-back is not overwritten."""
    summarise = point_summary.summarise

    def meanwhile(drafts, scale_factor, levels):
        chain.remove_observation(15, 0, refresh=False)
        chain.set_position(14, np.array([1.4, 0.0, 3.0]))
        return summarise(drafts, scale_factor, levels)

    for point_id in (13, 14, 15):
        chain.points[point_id].max_distance = np.inf
    monkeypatch.setattr(database, "summarise", meanwhile)
    chain.refresh_points(np.array([13, 14, 15]))
    assert np.isfinite(chain.points[13].max_distance)
    assert chain.points[14].max_distance == np.inf and chain.points[15].max_distance == np.inf


def test_adding_points_skips_keypoints_taken_while_it_computed(chain, monkeypatch):
    summarise = point_summary.summarise

    def meanwhile(drafts, scale_factor, levels):
        chain.add_observation(10, 0, 16, refresh=False)
        return summarise(drafts, scale_factor, levels)

    monkeypatch.setattr(database, "summarise", meanwhile)
    made = chain.add_points(np.array([[0.0, 0.1, 2.0], [0.1, 0.1, 2.0], [0.2, 0.1, 2.0]]),
                            [{0: 16, 2: 16}, {1: 17, 2: 17}, {0: 18, 7: 18}])
    assert len(made) == 1 and chain.points[made[0]].observations == {1: 17, 2: 17}
    assert chain.keyframes[2].point_ids[16] == -1 and chain.keyframes[0].point_ids[18] == -1
    single = chain.add_point(np.array([0.1, 0.1, 2.0]), {1: 19, 2: 19})
    np.testing.assert_allclose(chain.points[made[0]].normal, chain.points[single].normal)
    assert chain.points[made[0]].max_distance == pytest.approx(chain.points[single].max_distance)
