"""The SLAM map: observations, covisibility, local map queries, point culling and fusion."""

import numpy as np
import pytest

from services.slam.features import FrameFeatures
from services.slam.map import SlamMap


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
def chain() -> SlamMap:
    """Keyframes 0, 1, 2 along x; points 0-9 seen by 0 and 1, points 10-14 by 1 and 2, point 15 by all."""
    slam_map = SlamMap(1.2, 8)
    for k in range(3):
        slam_map.add_keyframe(k, pose(0.1 * k), features(20, k), np.full(20, -1))
    for i in range(10):
        slam_map.add_point(np.array([i * 0.1, 0.0, 2.0]), {0: i, 1: i})
    for i in range(10, 15):
        slam_map.add_point(np.array([i * 0.1, 0.0, 2.0]), {1: i, 2: i})
    slam_map.add_point(np.array([0.0, 0.5, 2.0]), {0: 15, 1: 15, 2: 15})
    return slam_map


def test_covisibility_counts_shared_points(chain):
    assert chain.covisibility(1) == {0: 11, 2: 6}
    assert chain.covisibility(0) == {1: 11, 2: 1}
    assert chain.covisible(0, 5, least=2) == [1]
    assert chain.keyframes[0].point_ids[:10].tolist() == list(range(10))


def test_local_map_of_matched_points(chain):
    assert chain.local_keyframes(np.array([10, 11]), 5) == [1, 2, 0]
    assert chain.local_keyframes(np.array([10, 11]), 1) == [1]
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


def test_culling_removes_recent_points_rarely_found_or_seen(chain):
    chain.count_visible(np.arange(5), found=np.zeros(5, bool))
    for _ in range(4):
        chain.count_visible(np.array([0, 1]))
    # points 0 and 1: found 1 of 6 times; 2-4: 1 of 2; 0-9 made in keyframe 0, 10-14 in keyframe 1
    assert chain.cull_points(1, min_found_ratio=0.25, min_observations=3, probation=3) == 2
    assert 0 not in chain.points and 1 not in chain.points and 2 in chain.points
    # two keyframes on, points seen by two keyframes only go
    assert chain.cull_points(2, min_found_ratio=0.25, min_observations=3, probation=3) == 8
    assert sorted(chain.points) == [10, 11, 12, 13, 14, 15]
    # past probation nothing is culled
    assert chain.cull_points(5, min_found_ratio=0.25, min_observations=3, probation=3) == 0


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
