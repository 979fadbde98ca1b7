"""``SourceClock``: a lossless source's frames stamped on its own clock, from the wall-clock time of the first."""

from __future__ import annotations

import time

from services.runtime.stamps import NOMINAL_S, SourceClock


def test_the_first_frame_is_stamped_now_and_the_next_ones_a_pace_apart():
    clock = SourceClock()
    before = time.time_ns()
    first = clock.stamp(None, 0.1)
    assert before <= first <= time.time_ns()
    time.sleep(0.05)  # held back: the stamps do not see it
    assert [clock.stamp(None, 0.1) - first for _ in range(3)] == [100_000_000, 200_000_000, 300_000_000]


def test_without_a_pace_the_frames_own_times_set_the_intervals():
    clock = SourceClock()
    first = clock.stamp(5_000_000_000)
    steps = [clock.stamp(own) - first for own in (5_040_000_000, 5_041_500_000, 6_000_000_000)]
    assert steps == [40_000_000, 41_500_000, 1_000_000_000]


def test_a_frame_without_a_later_own_time_comes_a_nominal_interval_after_the_last():
    clock = SourceClock()
    nominal = round(NOMINAL_S * 1e9)
    first = clock.stamp(2_000_000_000)
    started_over = clock.stamp(0)  # a looped source back at its start
    untimed = clock.stamp(None)
    again = clock.stamp(100_000_000)
    assert [started_over - first, untimed - first, again - first] == [nominal, 2 * nominal, 3 * nominal]
