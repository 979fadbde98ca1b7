"""Counters and timing windows behind NodeStats, on a fake clock where time matters."""

from __future__ import annotations

import time
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from protocol import StreamStats
from services.bus import stats
from services.bus.stats import AgeWindow, LatencyWindow, RateMeter, StreamCounter


class FakeClock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


@pytest.fixture
def clock(monkeypatch) -> FakeClock:
    """Replaces ``time.monotonic`` as the stats module sees it (and nowhere else)."""
    fake = FakeClock()
    monkeypatch.setattr(stats, "time", SimpleNamespace(monotonic=fake))
    return fake


durations = st.lists(st.floats(min_value=0, max_value=10), min_size=1, max_size=50)
quantiles = st.lists(st.floats(min_value=0, max_value=100), min_size=1, max_size=5)


@settings(max_examples=200, deadline=None)
@given(values=durations, qs=quantiles)
def test_percentiles_match_numpy_in_milliseconds(values: list[float], qs: list[float]):
    window = LatencyWindow()
    for value in values:
        window.add(value)
    expected = np.percentile(np.array(values) * 1e3, qs)
    assert window.percentiles_ms(*qs) == pytest.approx(tuple(expected), rel=1e-12, abs=1e-12)


@settings(max_examples=100, deadline=None)
@given(values=durations, size=st.integers(1, 10))
def test_window_keeps_only_the_last_values(values: list[float], size: int):
    window = LatencyWindow(size)
    for value in values:
        window.add(value)
    kept = values[-size:]
    assert len(window) == len(kept)
    assert window.percentiles_ms(0, 100) == pytest.approx((min(kept) * 1e3, max(kept) * 1e3))


def test_empty_window_has_no_percentiles():
    assert LatencyWindow().percentiles_ms(50, 99) == (None, None)


def test_median_of_known_durations():
    window = LatencyWindow()
    for seconds in (0.001, 0.002, 0.003, 0.010):
        window.add(seconds)
    assert window.percentiles_ms(50) == pytest.approx((2.5,))


def test_rate_counts_events_over_the_window(clock: FakeClock):
    meter = RateMeter(window_s=2.0)
    assert meter.rate() == 0.0
    meter.tick(3)
    clock.now += 1.0
    meter.tick()
    assert meter.rate() == 2.0  # 4 events / 2 s
    clock.now += 1.0
    assert meter.rate() == 2.0  # the first tick is exactly window_s old: still counted
    clock.now += 0.5
    assert meter.rate() == 0.5  # only the second tick is left
    clock.now += 2.0
    assert meter.rate() == 0.0


def test_steady_ticks_give_their_frequency(clock: FakeClock):
    meter = RateMeter(window_s=1.0)
    for _ in range(100):
        clock.now += 0.1
        meter.tick()
    assert meter.rate() == pytest.approx(10.0, abs=1.0)


def test_stream_counter_accumulates_and_snapshots(clock: FakeClock):
    counter = StreamCounter("ar/rig0/cam0/image", "in")
    counter.count(messages=3)
    counter.count(dropped=2, decode_errors=1)
    counter.count(messages=1, dropped=1)
    snapshot = counter.snapshot()
    assert snapshot == StreamStats(key="ar/rig0/cam0/image", direction="in", messages=4, dropped=3,
                                   decode_errors=1, rate_hz=2.0)


def test_stream_counter_rate_counts_messages_only(clock: FakeClock):
    counter = StreamCounter("ar/rig0/cam0/image", "in")
    counter.count(dropped=10, decode_errors=10)
    assert counter.snapshot().rate_hz == 0.0


def test_stream_counter_rate_forgets_old_messages(clock: FakeClock):
    counter = StreamCounter("ar/rig0/pose/x", "out")
    counter.count(messages=8)
    clock.now += 5.0
    snapshot = counter.snapshot()
    assert (snapshot.messages, snapshot.rate_hz) == (8, 0.0)


def test_age_window_counts_recent_stamps_only():
    ages = AgeWindow(max_s=10.0)
    now = 1_700_000_000_000_000_000
    assert ages.add_stamp(now - 2_000_000, now) and ages.add_stamp(now - 4_000_000, now)
    assert ages.add_stamp(now, now)  # an age of zero counts
    assert not ages.add_stamp(now + 1_000, now)  # stamped after now: another clock
    assert not ages.add_stamp(now - 10_000_000_001, now)  # older than max_s: a replay's recorded time
    assert len(ages) == 3
    assert ages.percentiles_ms(50, 100) == pytest.approx((2.0, 4.0))


def test_age_window_uses_the_wall_clock_by_default():
    ages = AgeWindow()
    assert ages.add_stamp(time.time_ns() - 5_000_000)
    (p50,) = ages.percentiles_ms(50)
    assert 5.0 <= p50 < 5.0 + 1e3 * ages.max_s
