"""Local mapping: the keyframe decision (and its wait for a busy mapper), the checks on triangulated
points, new points between two keyframes, and ``SlamSystem``'s behaviour on bad frames and with its
mapping thread or process."""

import threading
import time

import cv2
import numpy as np
import pytest

from protocol.tracking_state import TrackingState
from services.geometry.camera import CameraModel
from services.geometry.epipolar import near_lines
from services.geometry.evaluation import umeyama
from services.geometry.se3 import invert
from services.geometry.triangulation import meet_in_front, triangulate_midpoint
from services.slam.features import FeatureExtractor, FrameFeatures
from services.slam.frontend import Tracked, Tracker
from services.slam.map.database import MapDatabase
from services.slam.mapping import KeyframeDecision, LocalMapper, keyframe_decision, triangulation_checks
from services.slam.system import SlamSettings, SlamSystem
from services.synthetic import make_scene

SETTINGS = SlamSettings()
K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])


@pytest.mark.parametrize(("seconds", "tracked", "reference", "expected"), [
    (0.6, 200, 300, KeyframeDecision.IF_IDLE),   # new area: a keyframe if the mapper is idle...
    (1.2, 200, 300, KeyframeDecision.YES),       # ...and whatever it does once too long has passed
    (0.6, 290, 300, KeyframeDecision.NO),        # little new area
    (2.0, 290, 300, KeyframeDecision.NO),
    (0.2, 200, 300, KeyframeDecision.NO),        # too soon after the last keyframe
    (0.1, 40, 300, KeyframeDecision.YES),        # nearly lost
])
def test_keyframe_decision(seconds, tracked, reference, expected):
    assert keyframe_decision(SETTINGS, seconds, tracked, reference) is expected


BUSY_S = 0.2


class BusyUntilWaitedFor:
    """An inline ``LocalMapper`` that, after each keyframe it maps, says it is busy until the tracker
    waits for it (``wait_idle`` then takes ``BUSY_S``): a mapper slower than any frame rate."""

    def __init__(self, mapper: LocalMapper):
        self._mapper = mapper
        self.history = mapper.history
        self.busy = False
        self.waits = 0

    @property
    def idle(self) -> bool:
        return not self.busy

    def wait_idle(self, timeout_s: float) -> bool:
        self.waits += 1
        if self.busy:
            time.sleep(min(BUSY_S, timeout_s))
            self.busy = timeout_s < BUSY_S
        return not self.busy

    def enqueue(self, keyframe_id: int) -> None:
        self._mapper.enqueue(keyframe_id)
        self.busy = True

    def adjust_initial_map(self, first: int, second: int) -> None:
        self._mapper.adjust_initial_map(first, second)

    def resend(self) -> None:
        self._mapper.resend()

    def sync(self) -> None:
        """Nothing to bring in."""

    def close(self) -> None:
        self._mapper.close()


def track_room(camera: CameraModel, frames: int, wait_for_mapping: bool, s: SlamSettings = SETTINGS,
               ) -> tuple[list[Tracked], list[dict[str, float]], BusyUntilWaitedFor]:
    """The room's first ``frames`` frames through a ``Tracker`` (settings ``s``) mapping with ``BusyUntilWaitedFor``."""
    scene = make_scene("room")
    extractor = FeatureExtractor(camera, s.max_keypoints, s.levels, s.scale_factor, s.fast_threshold)
    slam_map = MapDatabase(s.scale_factor, s.levels)
    mapper = BusyUntilWaitedFor(LocalMapper(slam_map, camera.K, (camera.width, camera.height), s, threaded=False))
    tracker = Tracker(camera, s, slam_map, mapper, wait_for_mapping=wait_for_mapping)
    results, timings = [], []
    for index in range(frames):
        frame = scene.render(index)
        timings.append({})
        results.append(tracker.track(round(frame.time_s * 1e9), extractor.extract(frame.images["cam0"]), timings[-1]))
    return results, timings, mapper


@pytest.mark.slow
def test_each_keyframe_is_mapped_before_the_next_frame_when_asked(room_camera):
    waited, waited_timings, mapper = track_room(room_camera, 45, wait_for_mapping=True)
    initial, *made = [i for i, result in enumerate(waited) if result.keyframe_id is not None]
    asked = [i for i, timings in enumerate(waited_timings) if "mapping_wait" in timings]
    # every keyframe the tracker made was waited for at once, as long as the mapper was busy, and only then
    # (the initial map's is bundle adjusted before the frame's result, with no wait)
    assert initial < made[0] and asked == made and mapper.waits == len(made)
    assert all(waited_timings[i]["mapping_wait"] >= BUSY_S * 1e3 for i in made)
    real_time, real_time_timings, real_time_mapper = track_room(room_camera, 45, wait_for_mapping=False)
    # without the option the tracker waits only after a keyframe made on a nearly lost frame, and the busy
    # mapper holds keyframes back
    thin = [i for i, result in enumerate(real_time)
            if result.keyframe_id is not None and result.tracked < 2 * SETTINGS.min_tracked]
    assert real_time_mapper.waits == len(thin)
    assert [i for i, t in enumerate(real_time_timings) if "mapping_wait" in t] == thin
    assert sum(result.keyframe_id is not None for result in real_time) < 1 + len(made)


@pytest.mark.slow
def test_a_real_time_tracker_waits_for_the_mapper_after_a_keyframe_made_nearly_lost(room_camera):
    """With ``min_tracked`` raised so that the room's frames track fewer than twice it now and then, each
    keyframe made on such a frame is waited for (the next frames would find no map), and no other frame
    waits."""
    s = SETTINGS.model_copy(update={"min_tracked": 130})
    results, timings, mapper = track_room(room_camera, 45, wait_for_mapping=False, s=s)
    made = [i for i, result in enumerate(results) if result.keyframe_id is not None][1:]
    thin = [i for i in made if results[i].tracked < 2 * s.min_tracked]
    assert thin, [results[i].tracked for i in made]
    assert [i for i, t in enumerate(timings) if "mapping_wait" in t] == thin
    assert mapper.waits == len(thin) and all(timings[i]["mapping_wait"] >= BUSY_S * 1e3 for i in thin)


def test_the_mapping_thread_is_waited_for_until_its_keyframes_are_mapped(monkeypatch):
    mapper = LocalMapper(MapDatabase(1.2, 8), K, (640, 480), SETTINGS, threaded=True)
    release = threading.Event()
    mapped = []
    monkeypatch.setattr(mapper, "process", lambda keyframe_id, others_waiting=False: mapped.append(release.wait()))
    try:
        assert mapper.idle and mapper.wait_idle(0.0)
        mapper.enqueue(0)
        mapper.enqueue(1)
        assert not mapper.idle and not mapper.wait_idle(0.05)
        started, cpu = time.monotonic(), time.thread_time()
        threading.Timer(0.3, release.set).start()
        assert mapper.wait_idle(30.0)
        # woken when the last keyframe is mapped (never before the release), without spinning meanwhile
        assert time.monotonic() - started >= 0.3 and time.thread_time() - cpu < 0.05
        assert mapper.idle and mapped == [True, True]
    finally:
        release.set()
        mapper.close()


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
    slam_map = MapDatabase(1.2, 8)
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
        assert (result.state, result.reason, result.T_world_camera) == (TrackingState.INITIALISING, "bad_image", None)
    blank = system.process(1, np.zeros((480, 640), np.uint8))
    assert (blank.state, blank.reason) == (TrackingState.INITIALISING, "no_texture")


@pytest.mark.slow
@pytest.mark.parametrize("mapping", ["thread", pytest.param("process", marks=pytest.mark.integration)])
def test_room_tracked_while_mapping_apart(room_camera, mapping):
    """Every frame fed, as in a lossless run, whose keyframe decisions wait for the mapper
    (``wait_for_mapping``): a loaded machine, whose mapper is busy longer, makes no fewer keyframes."""
    scene = make_scene("room")
    system = SlamSystem(room_camera, SETTINGS.model_copy(update={"max_keypoints": 1000}), mapping=mapping,
                        wait_for_mapping=True)
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
    first = states.index(TrackingState.TRACKING)
    assert first < 30 and all(state is TrackingState.TRACKING for state in states[first:])
    assert [stamp for stamp, _ in system.trajectory()] == [round(f.time_s * 1e9) for f in frames[first:]]
    assert results[first].keyframe_id is not None and revision > 0
    keyframes = system.keyframe_poses()
    ids, positions = system.map_points()
    assert len(keyframes) >= 3 and len(ids) == len(positions) > 500
    np.testing.assert_allclose(keyframes[0][2], np.eye(4), atol=1e-9)


@pytest.mark.slow
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
        assert (result.state, result.reason, result.T_world_camera) == (TrackingState.LOST, "no_texture", None)
    # half a second later, the camera elsewhere: found again by PnP against the whole map
    frame = scene.render(75)
    result = system.process(round(frame.time_s * 1e9), frame.images["cam0"])
    assert result.state is TrackingState.TRACKING and result.tracked > 100
    # within 5 cm of the truth, through the similarity fitted to the first 52 tracked frames (a path
    # of 0.73 m, so its scale is known to a few per cent)
    alignment = umeyama(np.array(estimated), np.array(true), with_scale=True)
    error = np.linalg.norm(alignment.apply(result.T_world_camera[None, :3, 3])[0] - frame.truth["cam0"][0][2][:3, 3])
    assert error < 0.05
