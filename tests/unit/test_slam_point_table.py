"""The map's point table gives what the map points themselves hold, after every kind of change to the map."""

import numpy as np
import pytest

from services.slam.map.database import MapDatabase
from services.slam.map.map_point import PointArrays
from services.slam.map.point_table import FIRST_ROWS
from services.slam.map.sync import apply_changes, record_changes, restore, snapshot, take_changes
from services.slam.system import SlamSystem
from services.synthetic import make_scene
from tests.unit.test_slam_map import features, pose


def from_points(slam_map: MapDatabase, point_ids: np.ndarray) -> PointArrays:
    """The reference: the points' own fields gathered one point at a time."""
    points = [slam_map.points[i] for i in point_ids.tolist() if i in slam_map.points]
    return PointArrays(ids=np.array([p.id for p in points], np.int64),
                       positions=np.array([p.position for p in points], np.float64).reshape(-1, 3),
                       descriptors=np.array([p.descriptor for p in points], np.uint8).reshape(-1, 32),
                       normals=np.array([p.normal for p in points], np.float64).reshape(-1, 3),
                       min_distances=np.array([p.min_distance for p in points], np.float64),
                       max_distances=np.array([p.max_distance for p in points], np.float64))


def assert_same(slam_map: MapDatabase, point_ids: np.ndarray) -> None:
    got, expected = slam_map.arrays(point_ids), from_points(slam_map, point_ids)
    for name in ("ids", "positions", "descriptors", "normals", "min_distances", "max_distances"):
        np.testing.assert_array_equal(getattr(got, name), getattr(expected, name), err_msg=name)
    np.testing.assert_array_equal(slam_map.positions(point_ids), expected.positions)


def asked(slam_map: MapDatabase) -> np.ndarray:
    """Every id ever given and some never given, shuffled, a few twice."""
    ids = np.arange(-2, slam_map.next_point_id + 3)
    ids = np.r_[ids, ids[::7]]
    return np.random.default_rng(3).permutation(ids)


def test_every_change_of_the_database_reaches_the_table():
    slam_map = MapDatabase(1.2, 8)
    for k in range(3):
        slam_map.add_keyframe(k, pose(0.1 * k), features(40, k), np.full(40, -1))
    for i in range(30):
        slam_map.add_point(np.array([i * 0.1, 0.0, 2.0]), {0: i, 1: i})
    slam_map.add_points(np.array([[0.0, 0.3, 2.5], [0.1, 0.3, 2.5]]), [{1: 31, 2: 31}, {1: 32, 2: 32}])
    assert_same(slam_map, asked(slam_map))
    slam_map.set_position(3, np.array([0.3, 0.1, 2.2]))
    slam_map.add_observation(4, 2, 4)
    slam_map.remove_observation(5, 0)  # left with one observation: removed
    slam_map.remove_point(6)
    slam_map.merge_points(7, 8)
    slam_map.refresh_points(np.arange(10))
    assert 5 not in slam_map.points and 6 not in slam_map.points and 8 not in slam_map.points
    assert_same(slam_map, asked(slam_map))
    copy = MapDatabase(1.2, 8)
    restore(copy, snapshot(slam_map))
    assert_same(copy, asked(slam_map))
    record_changes(copy)
    copy.set_position(9, np.array([0.9, 0.2, 2.1]))
    copy.remove_point(10)
    apply_changes(slam_map, take_changes(copy), [])
    assert_same(slam_map, asked(slam_map))
    slam_map.clear()
    assert len(slam_map.arrays(np.arange(40))) == 0


def test_the_table_grows_past_its_first_rows():
    slam_map = MapDatabase(1.2, 8)
    slam_map.add_keyframe(0, pose(0.0), features(FIRST_ROWS + 10, 0), np.full(FIRST_ROWS + 10, -1))
    slam_map.add_keyframe(1, pose(0.1), features(FIRST_ROWS + 10, 1), np.full(FIRST_ROWS + 10, -1))
    for i in range(FIRST_ROWS + 5):
        slam_map.add_point(np.array([i * 1e-3, 0.0, 2.0]), {0: i, 1: i})
    assert_same(slam_map, asked(slam_map))


@pytest.mark.parametrize("mapping", ["inline", pytest.param("process", marks=pytest.mark.integration)])
def test_after_tracking_and_mapping_the_table_is_the_points(mapping):
    """Frames of the room tracked while mapping (inline, or in the mapping process whose changes come back)."""
    scene = make_scene("room")
    system = SlamSystem(scene.cameras[0], mapping=mapping, wait_for_mapping=True)
    try:
        for index in range(45):
            frame = scene.render(index)
            system.process(round(frame.time_s * 1e9), frame.images["cam0"])
    finally:
        system.close()
    assert len(system.map.keyframes) >= 3 and len(system.map.points) > 300
    assert_same(system.map, asked(system.map))
