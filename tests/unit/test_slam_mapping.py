"""Local mapping: the keyframe decision, the checks on triangulated points, new points between two
keyframes, and ``SlamSystem``'s behaviour on bad frames and with its mapping thread."""

import dataclasses

import cv2
import numpy as np
import pytest

from services.capture.scenes import make_scene
from services.geometry.camera import CameraModel
from services.geometry.epipolar import near_lines
from services.geometry.evaluation import umeyama
from services.geometry.se3 import invert
from services.geometry.triangulation import meet_in_front, triangulate_midpoint
from services.slam.features import FrameFeatures
from services.slam.map import SlamMap
from services.slam.mapping import LocalMapper, need_keyframe, triangulation_checks
from services.slam.system import SlamSettings, SlamState, SlamSystem

SETTINGS = SlamSettings()
K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])


@pytest.mark.parametrize(("seconds", "tracked", "reference", "idle", "expected"), [
    (0.6, 200, 300, True, True),     # new area, mapper idle
    (0.6, 290, 300, True, False),    # little new area
    (0.2, 200, 300, True, False),    # too soon after the last keyframe
    (0.6, 200, 300, False, False),   # the mapper is busy...
    (1.2, 200, 300, False, True),    # ...but too long has passed
    (0.1, 40, 300, False, True),     # nearly lost
])
def test_keyframe_decision(seconds, tracked, reference, idle, expected):
    assert need_keyframe(SETTINGS, seconds, tracked, reference, idle) is expected


def test_triangulation_checks():
    centres = np.array([[0.0, 0, 0], [0.2, 0, 0]])
    points = np.array([[0.0, 0, 2], [0.0, 0, 2], [0.0, 0, -2], [0.0, 0, 200], [0.0, 0, 2], [np.nan, 0, 2]])
    residuals = np.zeros((6, 2, 2))
    residuals[1, 1] = [3.0, 0.0]    # beyond sqrt(5.991) px at sigma 1
    depths = points[:, 2:].repeat(2, axis=1)
    sigmas = np.ones((6, 2))
    sigmas[4] = [1.0, 1.2**4]       # found on level 0 and 4 at the same distance
    kept = triangulation_checks(points, centres, residuals, depths, sigmas, min_parallax_deg=1.0)
    assert kept.tolist() == [True, False, False, False, False, False]
    residuals[1, 1] = [3.0, 0.0]
    sigmas[1] = 2.0
    assert triangulation_checks(points[:2], centres, residuals[:2], depths[:2], sigmas[:2], 1.0).tolist() == [True,
                                                                                                              True]


def test_rays_meet_in_front_as_the_midpoint_says():
    rng = np.random.default_rng(5)
    T_a, T_b = np.eye(4), np.eye(4)
    T_b[:3, :3] = cv2.Rodrigues(np.array([0.02, 0.1, -0.03]))[0]
    T_b[:3, 3] = [-0.4, 0.05, -0.2]
    pixels_a, pixels_b = rng.uniform(0, 640, (200, 2)), rng.uniform(0, 640, (200, 2))
    found = meet_in_front(K, T_a, T_b, pixels_a, pixels_b, np.arange(200), np.arange(200))
    expected = []
    for a, b in zip(pixels_a, pixels_b, strict=True):
        directions = np.array([np.linalg.solve(K, [*a, 1.0]), T_b[:3, :3].T @ np.linalg.solve(K, [*b, 1.0])])
        origins = np.array([np.zeros(3), invert(T_b)[:3, 3]])
        # the midpoint lies on the common perpendicular: along each ray, where that ray comes closest
        midpoint = triangulate_midpoint(origins, directions)
        expected.append(all((midpoint - origins[k]) @ directions[k] > 0 for k in range(2)))
    assert 20 < found.sum() < 180
    np.testing.assert_array_equal(found, expected)


def test_near_epipolar_lines_as_opencv_draws_them():
    """Pixels of image b within their bounds of the epipolar lines OpenCV computes for image a's pixels."""
    rng = np.random.default_rng(5)
    F = rng.normal(size=(3, 3))
    pixels_a, pixels_b = rng.uniform(0, 640, (150, 2)), rng.uniform(0, 480, (90, 2))
    bounds = rng.uniform(0.5, 80, 90)
    lines = cv2.computeCorrespondEpilines(pixels_a.reshape(-1, 1, 2), 1, F).reshape(-1, 3)
    distances = np.abs(lines[:, :2] @ pixels_b.T + lines[:, 2:]) / np.linalg.norm(lines[:, :2], axis=1)[:, None]
    rows, columns = near_lines(F, pixels_a, pixels_b, bounds)
    near = np.zeros((150, 90), bool)
    near[rows, columns] = True
    clear = np.abs(distances - bounds[None]) > 1e-3 * bounds[None]
    assert 0 < len(rows) < near.size and len(np.unique(rows * 90 + columns)) == len(rows)
    np.testing.assert_array_equal(near[clear], (distances < bounds[None])[clear])


def test_new_points_between_two_keyframes_are_where_the_scene_is():
    rng = np.random.default_rng(3)
    world = rng.uniform([-1.5, -1, 3], [1.5, 1, 5], (300, 3))
    descriptors = rng.integers(0, 256, (300, 32), dtype=np.uint8)
    slam_map = SlamMap(1.2, 8)
    poses = [np.eye(4), np.eye(4)]
    poses[1][:3, 3] = [-0.3, 0.0, 0.0]
    for T in poses:
        camera = world @ T[:3, :3].T + T[:3, 3]
        pixels = camera[:, :2] / camera[:, 2:] @ K[:2, :2].T + K[:2, 2]
        order = rng.permutation(300)
        frame = FrameFeatures(pixels[order] + rng.normal(0, 0.3, (300, 2)), np.zeros(300, np.int64),
                              np.zeros(300, np.float32), descriptors[order], np.ones(300))
        slam_map.add_keyframe(0, T, frame, np.full(300, -1))
    # one point each makes the keyframes covisible
    first, second = slam_map.keyframes[0], slam_map.keyframes[1]
    index = int(np.flatnonzero(np.all(first.features.descriptors == descriptors[0], axis=1))[0])
    other = int(np.flatnonzero(np.all(second.features.descriptors == descriptors[0], axis=1))[0])
    slam_map.add_point(world[0], {0: index, 1: other})
    mapper = LocalMapper(slam_map, K, (640, 480), SETTINGS, threaded=False)
    made = mapper.triangulate(1)
    assert made >= 280
    for point in list(slam_map.points.values())[1:]:
        truth = world[np.flatnonzero(np.all(descriptors == first.features.descriptors[point.observations[0]],
                                            axis=1))[0]]
        assert np.linalg.norm(point.position - truth) < 0.05 * truth[2]


@pytest.fixture(scope="module")
def room_camera() -> CameraModel:
    return make_scene("room").cameras[0]


def test_bad_frames_are_reported_not_raised(room_camera):
    system = SlamSystem(room_camera, mapping="inline")
    for image in (np.zeros((10, 10), np.uint8), np.zeros((480, 640), np.float32), np.zeros((480, 640, 2), np.uint8)):
        result = system.process(0, image)
        assert (result.state, result.reason, result.T_world_camera) == (SlamState.INITIALISING, "bad_image", None)
    blank = system.process(1, np.zeros((480, 640), np.uint8))
    assert (blank.state, blank.reason) == (SlamState.INITIALISING, "no_texture")


@pytest.mark.parametrize("mapping", ["thread", "process"])
def test_room_tracked_while_mapping_apart(room_camera, mapping):
    scene = make_scene("room")
    system = SlamSystem(room_camera, dataclasses.replace(SETTINGS, max_keypoints=1000), mapping=mapping)
    try:
        frames = [scene.render(i) for i in range(90)]
        results = [system.process(round(frame.time_s * 1e9), frame.images["cam0"]) for frame in frames]
        revision = system.map_revision
    finally:
        system.close()
    made = [r.keyframe_id for r in results if r.keyframe_id is not None]
    # every keyframe but the map's first two was mapped apart, timed stage by stage
    assert [record.keyframe_id for record in system._mapper.history] == made[1:]
    assert all(record.stages["triangulate"] > 0 and record.cpu_ms > 0 for record in system._mapper.history)
    assert all("map_sync" in r.timings_ms and "mapping" not in r.timings_ms for r in results)
    states = [r.state for r in results]
    first = states.index(SlamState.TRACKING)
    assert first < 30 and all(state is SlamState.TRACKING for state in states[first:])
    assert [stamp for stamp, _ in system.trajectory()] == [round(f.time_s * 1e9) for f in frames[first:]]
    assert results[first].keyframe_id is not None and revision > 0
    keyframes = system.keyframe_poses()
    ids, positions = system.map_points()
    assert len(keyframes) >= 3 and len(ids) == len(positions) > 500
    np.testing.assert_allclose(keyframes[0][2], np.eye(4), atol=1e-9)


def test_lost_on_blank_frames_then_relocalised(room_camera):
    scene = make_scene("room")
    system = SlamSystem(room_camera, mapping="inline")
    estimated, true = [], []
    for index in range(60):
        frame = scene.render(index)
        result = system.process(round(frame.time_s * 1e9), frame.images["cam0"])
        if result.T_world_camera is not None:
            estimated.append(result.T_world_camera[:3, 3])
            true.append(frame.truth["cam0"][0][2][:3, 3])
    for stamp, image in ((2_010_000_000, np.zeros((480, 640), np.uint8)), (2_020_000_000, np.full((480, 640), 128,
                                                                                                  np.uint8))):
        result = system.process(stamp, image)
        assert (result.state, result.reason, result.T_world_camera) == (SlamState.LOST, "no_texture", None)
    # half a second later, the camera elsewhere: found again by PnP against the whole map
    frame = scene.render(75)
    result = system.process(round(frame.time_s * 1e9), frame.images["cam0"])
    assert result.state is SlamState.TRACKING and result.tracked > 100
    # within 5 cm of the truth, through the similarity fitted to the first 52 tracked frames (a path
    # of 0.73 m, so its scale is known to a few per cent)
    alignment = umeyama(np.array(estimated), np.array(true), with_scale=True)
    error = np.linalg.norm(alignment.apply(result.T_world_camera[None, :3, 3])[0] - frame.truth["cam0"][0][2][:3, 3])
    assert error < 0.05
