"""A SLAM map kept in step with a copy through its changes: what the mapping process and the tracker exchange."""

import numpy as np
import pytest

from protocol.tracking_state import TrackingState
from services.slam.features import FrameFeatures
from services.slam.map import sync
from services.slam.map.database import MapDatabase
from services.slam.system import SlamSystem
from services.synthetic import make_scene


def assert_same_map(copy: MapDatabase, original: MapDatabase) -> None:
    assert copy.keyframes.keys() == original.keyframes.keys()
    for keyframe_id, keyframe in original.keyframes.items():
        np.testing.assert_array_equal(copy.keyframes[keyframe_id].T_camera_world, keyframe.T_camera_world)
        np.testing.assert_array_equal(copy.keyframes[keyframe_id].point_ids, keyframe.point_ids)
    assert copy.points.keys() == original.points.keys()
    for point_id, point in original.points.items():
        other = copy.points[point_id]
        np.testing.assert_array_equal(other.position, point.position)
        np.testing.assert_array_equal(other.descriptor, point.descriptor)
        np.testing.assert_array_equal(other.normal, point.normal)
        assert other.observations == point.observations and other.first_keyframe == point.first_keyframe
        assert (other.min_distance, other.max_distance) == (point.min_distance, point.max_distance)


@pytest.mark.slow
def test_a_copy_fed_the_changes_after_every_frame_stays_the_map():
    """Every change the tracker and the mapper make to a map (keyframes, triangulation, fusion, culling,
    bundle adjustment) reaches a copy restored from its snapshot and fed ``take_changes`` after each frame."""
    scene = make_scene("room")
    system = SlamSystem(scene.cameras[0], mapping="inline")
    copy = MapDatabase(system.map.scale_factor, system.map.levels)
    frames = (scene.render(index) for index in range(150))
    try:
        for frame in frames:
            result = system.process(round(frame.time_s * 1e9), frame.images["cam0"])
            if result.state is TrackingState.TRACKING and not len(copy.keyframes):
                sync.restore(copy, sync.snapshot(system.map))
                sync.record_changes(system.map)
                continue
            if len(copy.keyframes):
                if result.keyframe_id is not None:  # the tracker's copy makes its keyframes itself
                    made = system.map.keyframes[result.keyframe_id]
                    copy.add_keyframe(made.stamp_ns, made.T_camera_world, made.features, made.point_ids, made.id)
                sync.apply_changes(copy, sync.take_changes(system.map), pending=[])
        assert len(system.map.keyframes) >= 6 and len(system.map.points) >= 500
        assert system.map.replaced  # fusion merged points, and said which into which
        assert_same_map(copy, system.map)
    finally:
        system.close()


def _map_with_points(points: int = 4) -> tuple[MapDatabase, FrameFeatures]:
    rng = np.random.default_rng(1)
    features = FrameFeatures(rng.uniform(0, 640, (10, 2)), np.zeros(10, np.int64), np.zeros(10, np.float32),
                             rng.integers(0, 256, (10, 32), dtype=np.uint8), np.ones(10))
    slam_map = MapDatabase(1.2, 8)
    for shift in (0.0, 0.2):
        T = np.eye(4)
        T[0, 3] = shift
        slam_map.add_keyframe(0, T, features, np.full(10, -1))
    for k in range(points):
        slam_map.add_point(np.array([k * 0.1, 0.0, 3.0]), {0: k, 1: k})
    return slam_map, features


def test_a_pending_keyframe_keeps_its_observations_and_follows_merges():
    """The tracker's copy makes keyframe 2 while the mapper (which has not seen it) merges point 0 into 1
    and removes point 2: keyframe 2's keypoint of point 0 moves to point 1, that of point 2 is freed,
    and the points the changes replaced keep keyframe 2's observations."""
    mapper_map, features = _map_with_points()
    tracker_map = MapDatabase(1.2, 8)
    sync.restore(tracker_map, sync.snapshot(mapper_map))
    sync.record_changes(mapper_map)
    point_ids = np.full(10, -1)
    point_ids[[0, 2, 3]] = [0, 2, 3]
    pending = tracker_map.add_keyframe(0, np.eye(4), features, point_ids)
    mapper_map.merge_points(1, 0)
    mapper_map.remove_point(2)
    mapper_map.set_position(3, np.array([0.3, 0.0, 3.5]))
    sync.apply_changes(tracker_map, sync.take_changes(mapper_map), pending=[pending.id])
    assert pending.point_ids[[0, 2, 3]].tolist() == [1, -1, 3]
    assert tracker_map.points[1].observations == {0: 1, 1: 1, pending.id: 0}
    assert tracker_map.points[3].observations == {0: 3, 1: 3, pending.id: 3}
    np.testing.assert_array_equal(tracker_map.points[3].position, [0.3, 0.0, 3.5])
    assert set(tracker_map.points) == {1, 3} and tracker_map.resolve(np.array([0, 2, -1])).tolist() == [1, 2, -1]
    # the mapper, told of keyframe 2 only now, links it to the points its keypoints' points became
    mapper_map.add_keyframe(0, np.eye(4), features, point_ids, keyframe_id=pending.id)
    assert mapper_map.keyframes[pending.id].point_ids[[0, 2, 3]].tolist() == [1, -1, 3]


def test_tracking_counters_reach_the_mapper_once():
    mapper_map, _ = _map_with_points()
    tracker_map = MapDatabase(1.2, 8)
    sync.restore(tracker_map, sync.snapshot(mapper_map))
    sync.record_counts(tracker_map)
    tracker_map.count_visible(np.array([0, 1, 9]), np.array([True, False, True]))
    tracker_map.count_visible(np.array([0]))
    counts = sync.take_counts(tracker_map)
    assert counts == {0: (2, 1), 1: (1, 0)} and sync.take_counts(tracker_map) == {}
    sync.add_counts(mapper_map, counts)
    assert [(mapper_map.points[p].visible, mapper_map.points[p].found) for p in (0, 1, 2)] == [(3, 2), (2, 1), (1, 1)]


@pytest.mark.parametrize("mapping", ["threads", "", None])
def test_an_unknown_mapping_mode_is_refused(mapping):
    with pytest.raises(ValueError, match="one of process, thread, inline"):
        SlamSystem(make_scene("room").cameras[0], mapping=mapping)
