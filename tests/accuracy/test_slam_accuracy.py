"""Monocular SLAM (``SlamSystem``) against ground truth: ATE RMSE after a Sim(3) alignment, every frame
tracked from the first tracked one on, none lost (``tests/accuracy/slam_sequences.py`` runs the
sequences; its ``__main__`` prints the figures).

Every sequence runs as users run SLAM: local mapping in a process of its own, the frames fed back to
back as a lossless run feeds them (keyframe decisions wait for the mapper). The room meets its bars
so. KITTI and TUM do not: the tracker outruns the mapping process, a keyframe's new points reaching it
after the frames that needed them (docs/slam.md, known limits; KITTI lost 42 of 51 frames, TUM 10 of
19, a count that depends on the load). Those runs are expected to fail (``OUTRUN``), their bars
unchanged; the same bars hold with inline mapping (each keyframe mapped before the next frame), the
algorithms' own accuracy.

Two trajectories are scored. The final one (``SlamSystem.trajectory``: each tracked frame through its
reference keyframe's bundle-adjusted pose, what SLAM benchmarks score and what a user exports at the
end) is held to the bars: the synthetic ``room`` (600 frames) within 1 % of its path length; KITTI 06
frames 0-50 within 0.05 m; TUM fr3 long_office_household at about 1 Hz within 0.02 m. The online
poses (each frame's as tracked, what the bus carries live) have looser bars near their measured
figures, so that a regression shows: the room within 1 % too, KITTI within 0.08 m (measured
0.057 m), TUM within 0.025 m (measured 0.017 m).
"""

import pytest

from tests.accuracy.slam_sequences import KITTI, TUM, SlamRun, kitti, room, run, tum
from tests.data import data_dir

pytestmark = [pytest.mark.integration, pytest.mark.slow]


def check(result: SlamRun, final_bar_m: float, online_bar_m: float) -> None:
    print(result.line())
    assert result.first_tracked < len(result.states), f"{result.name}: never initialised"
    assert result.lost == 0, result.line()
    assert result.untracked_after_start == 0, result.line()
    assert result.final_ate_m <= final_bar_m, result.line()
    assert result.ate_m <= online_bar_m, result.line()


OUTRUN = pytest.mark.xfail(raises=AssertionError, strict=False, reason=(
    "fed back to back, the tracker outruns the mapping process and loses the map (docs/slam.md, known limits)"))
"""A mapping process that new keyframes' points reach too late for the frames that follow."""
MAPPINGS = [pytest.param("process", marks=OUTRUN), "inline"]


def test_room_trajectory_within_one_percent_of_its_length():
    result = run(room())
    check(result, 0.01 * result.length_m, 0.01 * result.length_m)


@pytest.mark.parametrize("mapping", MAPPINGS)
def test_kitti_06_trajectory_within_5_cm(mapping):
    check(run(kitti(data_dir(KITTI)), mapping), 0.05, 0.08)


@pytest.mark.parametrize("mapping", MAPPINGS)
def test_tum_long_office_1hz_trajectory_within_2_cm(mapping):
    check(run(tum(data_dir(TUM)), mapping), 0.02, 0.025)
