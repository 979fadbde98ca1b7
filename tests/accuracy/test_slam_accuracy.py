"""Monocular SLAM (``SlamSystem``) against ground truth: ATE RMSE after a Sim(3) alignment, the map started
by frame ``FIRST_TRACKED_BY``, every frame tracked from the first tracked one on, none lost
(``tests/accuracy/slam_sequences.py`` runs the sequences; its ``__main__`` prints the figures).

Every sequence runs as users run SLAM: local mapping in a process of its own, the frames fed back to
back as a lossless run feeds them (each new keyframe mapped before the next frame is tracked, so the
figures do not depend on the load). The same figures come from mapping inline, held by
``test_the_mapping_process_tracks_as_inline_mapping_does``.

Two trajectories are scored. The final one (``SlamSystem.trajectory``: each tracked frame through its
reference keyframe's bundle-adjusted pose, what SLAM benchmarks score and what a user exports at the
end) is held to the bars: the synthetic ``room``'s first ``ROOM_TEST_FRAMES`` frames within 1 % of their path
length (all ``ROOM_FRAMES`` of it are ``python -m tests.accuracy.slam_sequences room``'s); KITTI 06
frames 0-50 within 0.05 m; TUM fr3 long_office_household at about 1 Hz within 0.02 m. The online
poses (each frame's as tracked, what the bus carries live) have looser bars near their measured
figures, so that a regression shows: the room within 1 % too, KITTI within 0.08 m (measured
0.057 m), TUM within 0.025 m (measured 0.016 m).
"""

import numpy as np
import pytest

from tests.accuracy.slam_sequences import (
    KITTI,
    TUM,
    SlamRun,
    busy_stamped,
    every,
    first,
    kitti,
    room,
    run,
    tum,
    without,
)
from tests.data import data_dir

pytestmark = [pytest.mark.integration, pytest.mark.slow]

JITTER_SEEDS = range(100, 106)
ROOM_TEST_FRAMES = 300
"""10 s of the room, 3.45 m of path (0.56 % final and 0.51 % online ATE measured): half its frames."""
FIRST_TRACKED_BY = 4
"""Every sequence is tracked from this frame or earlier (room 4, KITTI 2, TUM 1)."""


def check(result: SlamRun, final_bar_m: float, online_bar_m: float) -> None:
    print(result.line())
    assert result.first_tracked <= FIRST_TRACKED_BY, result.line()
    assert result.lost == 0, result.line()
    assert result.untracked_after_start == 0, result.line()
    assert result.final_ate_m <= final_bar_m, result.line()
    assert result.ate_m <= online_bar_m, result.line()


def test_room_trajectory_within_one_percent_of_its_length():
    result = run(first(room(), ROOM_TEST_FRAMES))
    check(result, 0.01 * result.length_m, 0.01 * result.length_m)


def test_the_room_holds_its_accuracy_whatever_the_gaps_between_the_frames_stamps():
    """A pipeline that stamps frames by the wall clock and waits for SLAM gives it gaps that follow the
    load, and the keyframes follow the gaps. Over JITTER_SEEDS such stampings of the room's first 60
    frames (0.76 m of path tracked), every run stays within 3 % of the path and the median within 1.5 %
    (measured: 0.80-1.35 %, median 1.03 %). A local bundle adjustment whose scale followed the map's
    second keyframe, 2 cm from the first, once shrank the map by a third: 11.5 % for stamping 101."""
    runs = [run(busy_stamped(first(room(), 60), seed), "inline") for seed in JITTER_SEEDS]
    for result in runs:
        print(result.line())
        assert result.lost == 0 and result.untracked_after_start == 0, result.line()
    ates = np.array([result.ate_m / result.length_m for result in runs])
    print(f"online ATE over {len(runs)} stampings: min {ates.min():.2%}, median {np.median(ates):.2%}, "
          f"max {ates.max():.2%} of the path")
    assert ates.max() <= 0.03 and np.median(ates) <= 0.015, ates


def test_kitti_06_trajectory_within_5_cm():
    check(run(kitti(data_dir(KITTI))), 0.05, 0.08)


@pytest.mark.parametrize("gaps", [[range(15, 18)], [range(25, 29), range(40, 42)]], ids=["15-17", "25-28,40-41"])
def test_kitti_keeps_its_track_over_frames_a_busy_pipeline_dropped(gaps):
    """A car at 11 m/s is 3-4 m further after three or four frames dropped, past most of the points its
    map had in view: the next frame is bridged from the last tracked one (``services.slam.bridging``)
    instead of being lost for good. At most one frame untracked after each gap; final ATE within 8 cm and
    online within 15 cm (measured 6.0 / 8.7 cm and 5.5 / 11.6 cm; 3.9 / 5.7 cm with every frame)."""
    result = run(without(kitti(data_dir(KITTI)), {frame for gap in gaps for frame in gap}))
    print(result.line())
    assert result.untracked_after_start <= len(gaps), result.line()
    assert result.final_ate_m <= 0.08 and result.ate_m <= 0.15, result.line()


def test_a_young_map_lost_on_fast_forward_motion_starts_again_in_its_world():
    """KITTI 06 with three frames in four dropped (4.5 m between the frames kept): a map made of the first
    frames is lost within a few frames, as its points fall behind the car. A map lost while young is given
    up for a new one, placed and scaled where the camera's last motion carries it (``SlamSystem``'s
    ``restart_keyframes``), instead of waiting to relocalise in it while the car drives on: 8 of the 13
    frames tracked against 3 with ``restart_keyframes=0`` (the first map lost and never again), all in one
    world and scale, final and online ATE 0.092 and 0.067 m over the 38.4 m path. Bars: 7 frames, 0.3 m (a
    new map of its own world and scale, aligned with the first by one Sim(3), would be metres off)."""
    result = run(every(kitti(data_dir(KITTI)), 4))
    print(result.line())
    assert result.maps_given_up >= 1 and result.scored >= 7, result.line()
    assert result.final_ate_m <= 0.3 and result.ate_m <= 0.3, result.line()


def test_tum_long_office_1hz_trajectory_within_2_cm():
    check(run(tum(data_dir(TUM))), 0.02, 0.025)


def test_the_mapping_process_tracks_as_inline_mapping_does():
    apart, inline = run(tum(data_dir(TUM)), "process"), run(tum(data_dir(TUM)), "inline")
    assert apart.states == inline.states
    assert apart.final_ate_m == pytest.approx(inline.final_ate_m, abs=1e-9)
    assert apart.ate_m == pytest.approx(inline.ate_m, abs=1e-9)
