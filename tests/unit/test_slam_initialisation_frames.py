"""``SlamSystem`` while it initialises: which frames are tried, and when a map starts.

The room (30 fps, the camera speeding up from rest) and the KITTI 06 excerpt (a car driving forward at
10 Hz) from their first frame, mapping inline."""

from __future__ import annotations

import numpy as np

from protocol.tracking_state import TrackingState
from services.geometry.evaluation import absolute_trajectory_error
from services.slam.system import SlamSystem
from tests.accuracy.slam_sequences import KITTI, kitti
from tests.data import data_dir
from tests.slam_passes import room_frames, room_scene

KITTI_BY_FRAME = 5
"""The forward-motion excerpt is tracked from this frame or earlier."""


def test_the_room_is_tried_on_every_frame_and_starts_its_map_on_frame_8():
    """Every frame before the map is tried (matched: a ``match`` stage) and waits in ``low_parallax``;
    the map starts on frame 8, the first pair whose parallax passes the bound."""
    scene = room_scene()
    system = SlamSystem(scene.cameras[0], mapping="inline")
    results = []
    try:
        for stamp_ns, image, _ in room_frames(scene, range(12)):
            results.append(system.process(stamp_ns, image))
    finally:
        system.close()
    states = [r.state for r in results]
    first = states.index(TrackingState.TRACKING)
    assert first == 8 and all(state is TrackingState.TRACKING for state in states[first:])
    assert all(r.reason == "low_parallax" and "match" in r.timings_ms for r in results[1:first])


def test_forward_motion_is_tracked_within_the_first_frames():
    """KITTI 06's first frames: the pair of frame 0 and frame 1 has too little parallax, a later one
    starts the map, by frame ``KITTI_BY_FRAME``; every frame from then on is tracked, within 0.5 m of
    the truth after a Sim(3) alignment (the car drives about 1 m a frame)."""
    sequence = kitti(data_dir(KITTI))
    system = SlamSystem(sequence.camera, mapping="inline")
    states, estimated, true = [], [], []
    try:
        for index, (stamp_ns, image, T_true) in enumerate(sequence.frames):
            if index > KITTI_BY_FRAME + 3:
                break
            result = system.process(stamp_ns, image)
            states.append(result.state)
            if result.T_world_camera is not None:
                estimated.append(result.T_world_camera)
                true.append(T_true)
    finally:
        system.close()
    first = states.index(TrackingState.TRACKING)
    assert first <= KITTI_BY_FRAME and all(state is TrackingState.TRACKING for state in states[first:])
    assert len(estimated) >= 4
    assert absolute_trajectory_error(np.array(estimated), np.array(true), "sim3").stats.rmse < 0.5
