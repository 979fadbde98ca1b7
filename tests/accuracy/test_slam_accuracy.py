"""Monocular SLAM (``SlamSystem``, inline mapping) against ground truth: ATE RMSE after a Sim(3)
alignment, every frame tracked from the first tracked one on, none lost
(``tests/accuracy/slam_sequences.py`` runs the sequences; its ``__main__`` prints the figures).

Bars: the synthetic ``room`` (600 frames) within 1 % of its path length; KITTI 06 frames 0-50
within 0.05 m (offline COLMAP: 0.025 m); TUM fr3 long_office_household at about 1 Hz within
0.02 m (offline COLMAP: 0.009 m).
"""

import pytest

from tests.accuracy.slam_sequences import KITTI, TUM, SlamRun, kitti, room, run, tum
from tests.data import data_dir


def check_tracking(result: SlamRun) -> None:
    assert result.first_tracked < len(result.states), f"{result.name}: never initialised"
    assert result.lost == 0, result.line()
    assert result.untracked_after_start == 0, result.line()


def test_room_trajectory_within_one_percent_of_its_length():
    result = run(room())
    print(result.line())
    check_tracking(result)
    assert result.ate_m <= 0.01 * result.length_m, result.line()


@pytest.mark.xfail(strict=True, reason="measured ATE 0.057 m over 49 frames (bar 0.05 m; its keyframes after local "
                                       "bundle adjustment: 0.040 m): each frame tracks only 40-90 points, forward "
                                       "motion leaving few with enough parallax")
def test_kitti_06_trajectory_within_5_cm():
    result = run(kitti(data_dir(KITTI)))
    print(result.line())
    check_tracking(result)
    assert result.ate_m <= 0.05, result.line()


def test_tum_long_office_1hz_trajectory_within_2_cm():
    result = run(tum(data_dir(TUM)))
    print(result.line())
    check_tracking(result)
    assert result.ate_m <= 0.02, result.line()
