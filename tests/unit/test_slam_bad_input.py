"""``SlamSystem`` on bad input, over the room scene: frames without texture, jumps, frames out of order,
frame formats and sizes. Each bad frame comes back lost (or skipped) with its reason, never an
exception, and tracking goes on or recovers: the poses of the frames after it are checked against
the truth after the Sim(3) alignment of the whole run.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass

import numpy as np
import pytest

from protocol.tracking_state import TrackingState
from services.detection.grey import MONO16_SCALE
from services.geometry.evaluation import absolute_trajectory_error
from services.slam.system import FrameResult, SlamSystem
from tests.slam_passes import room_frames, room_scene

MAPPED = 60
"""Frames of the room mapped before the bad input (tracked from frame 4 on)."""
MAX_ERROR_M = 0.05
"""Largest position error of a frame after the bad input (the room's first 60 frames: a 0.7 m path)."""
BLANKS = {"black": np.zeros((480, 640), np.uint8), "grey": np.full((480, 640), 128, np.uint8),
          "white": np.full((480, 640), 255, np.uint8)}


@dataclass
class Run:
    """What a system gave for each frame fed, and the frame's true ``T_world_camera`` (None for a frame
    that is not the scene's)."""

    results: list[FrameResult]
    truth: list[np.ndarray | None]

    def errors_m(self) -> dict[int, float]:
        """Position error (m) of every posed frame with a truth, by its place in the run, after the
        Sim(3) alignment of them all."""
        rows = [i for i, (r, T) in enumerate(zip(self.results, self.truth, strict=True))
                if r.T_world_camera is not None and T is not None]
        estimated = np.array([self.results[i].T_world_camera for i in rows])
        ate = absolute_trajectory_error(estimated, np.array([self.truth[i] for i in rows]), "sim3")
        return dict(zip(rows, ate.errors.tolist(), strict=True))


@pytest.fixture(scope="module")
def scene():
    return room_scene()


def feed(system: SlamSystem, run: Run, scene, index: int, image: np.ndarray | None = None,
         stamp_ns: int | None = None, *, same_view: bool = False) -> FrameResult:
    """Frame ``index`` of ``scene`` into ``system`` and ``run``; ``image`` in its place is not the
    scene's (no truth) unless ``same_view``; ``stamp_ns`` in place of its own."""
    own_stamp, own, T_true = next(room_frames(scene, [index]))
    result = system.process(own_stamp if stamp_ns is None else stamp_ns, own if image is None else image)
    run.results.append(result)
    run.truth.append(T_true if image is None or same_view else None)
    return result


def mapped(scene, frames: int = MAPPED) -> tuple[SlamSystem, Run]:
    """A system (inline mapping) that tracked the room's first ``frames`` frames."""
    system = SlamSystem(scene.cameras[0], mapping="inline")
    run = Run([], [])
    for index in range(frames):
        feed(system, run, scene, index)
    assert run.results[-1].state is TrackingState.TRACKING
    return system, run


def assert_tracked_well(run: Run, first: int) -> None:
    """Every frame of ``run`` from ``first`` on that is the scene's is tracked (with no reason: the camera
    matrix passed its check), within ``MAX_ERROR_M``."""
    errors = run.errors_m()
    for place in range(first, len(run.results)):
        if run.truth[place] is not None:
            assert (run.results[place].state, run.results[place].reason) == (TrackingState.TRACKING, ""), place
            assert errors[place] < MAX_ERROR_M, (place, errors[place])


@pytest.mark.slow
def test_textureless_frames_before_the_map_wait_then_the_map_starts(scene):
    system = SlamSystem(scene.cameras[0], mapping="inline")
    run = Run([], [])
    for image in BLANKS.values():
        result = feed(system, run, scene, 0, image, stamp_ns=len(run.results))
        assert (result.state, result.reason, result.T_world_camera) == (TrackingState.INITIALISING, "no_texture", None)
    for index in range(1, 40):
        feed(system, run, scene, index)
    states = [r.state for r in run.results]
    assert TrackingState.TRACKING in states and states[-1] is TrackingState.TRACKING
    system.close()


@pytest.mark.slow
def test_textureless_and_noise_frames_are_lost_then_relocalised(scene):
    system, run = mapped(scene)
    noise = np.random.default_rng(5).integers(0, 256, (480, 640), np.uint8)
    for index, (name, image) in enumerate([*BLANKS.items(), ("noise", noise)], start=MAPPED):
        result = feed(system, run, scene, index, image)
        assert result.state is TrackingState.LOST and result.T_world_camera is None, name
        expected = ("no_texture",) if name != "noise" else ("no_candidates", "too_few_matches", "not_confirmed")
        assert result.reason in expected, (name, result.reason)
    back = feed(system, run, scene, MAPPED + 4)
    assert back.state is TrackingState.TRACKING and "relocalise_candidates" in back.timings_ms
    for index in range(MAPPED + 5, MAPPED + 30):
        feed(system, run, scene, index)
    assert_tracked_well(run, MAPPED + 4)
    system.close()


def stamp_of(scene, index: int) -> int:
    return next(room_frames(scene, [index]))[0]


@pytest.mark.slow
def test_a_frame_of_elsewhere_in_the_sequence_then_the_sequence_goes_on(scene):
    """Frame 1310 (43 s on, near frame 92: outside the mapped stretch) comes at frame 60's stamp."""
    system, run = mapped(scene)
    jump = feed(system, run, scene, 1310, stamp_ns=stamp_of(scene, MAPPED))
    print(f"frame 1310 at frame {MAPPED}'s stamp: {jump.state} {jump.reason}")
    for index in range(MAPPED + 1, MAPPED + 30):
        feed(system, run, scene, index)
    if jump.state is TrackingState.LOST:
        assert jump.reason in ("no_candidates", "too_few_matches", "not_confirmed") and jump.T_world_camera is None
    assert_tracked_well(run, MAPPED + 2 if jump.state is TrackingState.LOST else MAPPED)
    system.close()


@pytest.mark.slow
def test_a_frame_stamped_far_ahead_then_the_sequence_goes_on_and_keeps_making_keyframes(scene):
    """Frame 1200 (40 s on, 27 cm and 15 deg from the nearest pose of the mapped stretch: half new) with its
    own stamp becomes a keyframe, then frames 60 on come: the sequence stepped back by 38 s, more than
    ``STEP_BACK_S``, so they are tracked, not skipped, and keyframes are made again at their usual pace
    (the time since the last keyframe is taken either way)."""
    system, run = mapped(scene)
    ahead = feed(system, run, scene, 1200)
    assert ahead.state is TrackingState.TRACKING and ahead.keyframe_id is not None, ahead
    results = [feed(system, run, scene, index) for index in range(MAPPED, MAPPED + 60)]
    assert_tracked_well(run, MAPPED)
    made = [place for place, r in enumerate(results) if r.keyframe_id is not None]
    assert len(made) >= 3 and made[0] < 20, made
    system.close()


@pytest.mark.slow
def test_frames_out_of_order_are_skipped_and_a_step_far_back_is_tracked(scene, caplog):
    system, run = mapped(scene)
    with caplog.at_level(logging.WARNING, logger="services.slam.system"):
        earlier = system.process(stamp_of(scene, MAPPED - 10), next(room_frames(scene, [MAPPED - 10]))[1])
        feed(system, run, scene, MAPPED)
        twice = system.process(stamp_of(scene, MAPPED), next(room_frames(scene, [MAPPED]))[1])
    for result in (earlier, twice):
        assert (result.state, result.reason, result.T_world_camera) == (TrackingState.LOST, "out_of_order", None)
    assert len([r for r in caplog.records if "out of order" in r.getMessage()]) == 2
    following = feed(system, run, scene, MAPPED + 1)
    assert following.state is TrackingState.TRACKING and "relocalise_candidates" not in following.timings_ms
    back = feed(system, run, scene, 0)  # 2 s back: the sequence jumped, tracked in the map
    assert back.state is TrackingState.TRACKING, back.reason
    for index in range(MAPPED + 2, MAPPED + 20):
        feed(system, run, scene, index)
    assert_tracked_well(run, MAPPED)
    system.close()


def formats(grey: np.ndarray) -> list[np.ndarray]:
    """The grey (H, W) uint8 frame as mono8, bgr8, bgra8, mono16 and 16-bit BGR."""
    bgr = np.repeat(grey[:, :, None], 3, axis=2)
    mono16 = grey.astype(np.uint16) * np.uint16(MONO16_SCALE)
    return [grey, bgr, np.dstack([bgr, np.full_like(grey, 255)]), mono16, np.repeat(mono16[:, :, None], 3, axis=2)]


@pytest.mark.slow
def test_grey_colour_and_16_bit_frames_track_alike_and_unusable_ones_are_skipped(scene, caplog):
    system = SlamSystem(scene.cameras[0], mapping="inline")
    run = Run([], [])
    for index in range(MAPPED):
        grey = next(room_frames(scene, [index]))[1]
        result = feed(system, run, scene, index, formats(grey)[index % 5], same_view=True)
    assert result.state is TrackingState.TRACKING
    unusable = [np.zeros((240, 320), np.uint8), np.zeros((480, 640), np.float32), np.zeros((480, 640), np.int16),
                np.zeros((480, 640, 1), np.uint8), np.zeros((480, 640, 2), np.uint8), np.zeros(640 * 480, np.uint8),
                np.zeros((640, 480), np.uint8)]
    with caplog.at_level(logging.WARNING, logger="services.slam.system"):
        for offset, image in enumerate(unusable):
            skipped = system.process(stamp_of(scene, MAPPED) + offset, image)
            assert (skipped.state, skipped.reason, skipped.T_world_camera) == (TrackingState.LOST, "bad_image", None)
    assert len([r for r in caplog.records if "frame skipped" in r.getMessage()]) == len(unusable)
    following = feed(system, run, scene, MAPPED)
    assert following.state is TrackingState.TRACKING and "relocalise_candidates" not in following.timings_ms
    assert_tracked_well(run, 10)
    system.close()


@pytest.mark.parametrize("entry, value", [((0, 0), 0.0), ((1, 1), -512.0), ((0, 2), np.nan), ((0, 2), -100.0),
                                          ((1, 2), 480.0)])
def test_a_camera_matrix_slam_cannot_use_is_refused_in_one_line(scene, entry, value):
    K = scene.cameras[0].K.copy()
    K[entry] = value
    with pytest.raises(ValueError, match=r"^camera cam0: fx .* principal point .* 640x480 image$"):
        SlamSystem(dataclasses.replace(scene.cameras[0], K=K), mapping="inline")


@pytest.mark.slow
@pytest.mark.parametrize("fx_scale, principal_shift", [(1.3, (0, 0)), (0.7, (0, 0)), (1.0, (60, -45))])
def test_a_wrong_camera_matrix_is_reported_on_every_tracked_frame_after_the_check(scene, caplog, fx_scale,
                                                                                   principal_shift):
    """A focal length 30 % off, or the principal point 75 px away: tracking goes on (the map bends to fit),
    but once the map holds ``CHECK_KEYFRAMES`` keyframes each tracked frame says ``calibration_suspect``,
    after one warning line."""
    camera = scene.cameras[0]
    K = camera.K.copy()
    K[[0, 1], [0, 1]] *= fx_scale
    K[:2, 2] += principal_shift
    system = SlamSystem(dataclasses.replace(camera, K=K), mapping="inline")
    run = Run([], [])
    with caplog.at_level(logging.WARNING, logger="services.slam.system"):
        for index in range(MAPPED):
            feed(system, run, scene, index)
    system.close()
    checked = next(place for place, r in enumerate(run.results) if "calibration_check" in r.timings_ms)
    errors = run.errors_m()
    print(f"fx x{fx_scale}, principal point {principal_shift}: checked at frame {checked}, position error RMS "
          f"{np.sqrt(np.mean(np.square(list(errors.values())))):.3f} m after Sim(3); {caplog.records[0].getMessage()}")
    assert all(r.state is TrackingState.TRACKING and r.reason == "calibration_suspect" for r in run.results[checked:])
    assert [r.levelname for r in caplog.records] == ["WARNING"] and "calibration looks wrong" in caplog.text
