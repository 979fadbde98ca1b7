"""Replay timing without a bus: the pacer's time line, and passes over real files."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import pytest

from protocol import Header, Pose, encode
from services.recorder.playback import Pacer, Window, play_pass
from services.recorder.reading import Recorded, Scan
from services.recorder.writing import RecordingWriter

MS = 1_000_000
STALL_MS = 100
"""Later than due by this much is a stall, not the scheduling jitter of a busy machine (replay's timing
on an idle one is the recorder benchmark's: p99 about 1 ms)."""


class FakeClock:
    def __init__(self) -> None:
        self.now = 0

    def __call__(self) -> int:
        return self.now


def recording(path: Path, gaps_ms: list[int], keys: tuple[str, ...] = ("ar/r/pose/a",)) -> Path:
    """Poses whose log times are ``gaps_ms`` apart (the first at 5 s), cycling over ``keys``; many chunks."""
    writer = RecordingWriter(path)
    log_time = 5_000 * MS
    for i, gap in enumerate([0, *gaps_ms]):
        log_time += gap * MS
        writer.write(keys[i % len(keys)], encode(Pose(header=Header(stamp_ns=i, seq=i), child_frame_id="a")),
                     log_time)
        writer.flush()
    writer.close()
    return path


class Readings:
    """The monotonic clock (ns), keeping every reading."""

    def __init__(self) -> None:
        self.values: list[int] = []

    def __call__(self) -> int:
        self.values.append(time.monotonic_ns())
        return self.values[-1]


class Published:
    """A publish callback that notes each message's sequence number and monotonic time."""

    def __init__(self) -> None:
        self.seqs: list[int] = []
        self.times: list[int] = []

    def __call__(self, recorded: Recorded) -> None:
        self.times.append(time.monotonic_ns())
        self.seqs.append(recorded.message.sequence)


def test_the_position_advances_at_rate_and_stands_still_while_paused():
    clock = FakeClock()
    pacer = Pacer(2.0, clock=clock)
    pacer.anchor(1_000)
    clock.now += 500
    assert pacer.position_ns() == 2_000
    pacer.pause()
    clock.now += 10_000
    assert pacer.position_ns() == 2_000 and pacer.state == "paused"
    pacer.resume()
    clock.now += 100
    assert pacer.position_ns() == 2_200 and pacer.state == "playing"
    assert pacer.wait_for(2_100) == clock.now - 50  # already due: returns the clock time it was due
    pacer.step()
    assert pacer.wait_for(9_000) == clock.now and pacer.position_ns() == 9_000  # a step jumps to the message
    assert pacer.state == "paused"
    pacer.stop()
    assert pacer.wait_for(9_001) is None and pacer.state == "stopped"
    with pytest.raises(ValueError, match="rate must be positive"):
        Pacer(0)


def test_a_pass_keeps_the_recorded_gaps_divided_by_the_rate(tmp_path):
    path = recording(tmp_path / "r.mcap", [40, 80, 40, 120, 40])
    published, readings = Published(), Readings()
    done = play_pass(path, Pacer(4.0), published, clock=readings)
    assert published.seqs == list(range(6)) and done.played == done.read == 6
    due = [reading - late for reading, late in zip(readings.values, done.lateness_ns, strict=True)]
    assert [b - a for a, b in zip(due, due[1:], strict=False)] == [10 * MS, 20 * MS, 10 * MS, 30 * MS, 10 * MS]
    assert min(done.lateness_ns) >= 0 and max(done.lateness_ns) < STALL_MS * MS  # never early, never stalled
    assert done.damage is None and not done.stopped
    assert done.last_ns == 320 * MS


def test_a_window_and_a_selection_choose_what_is_played(tmp_path):
    path = recording(tmp_path / "r.mcap", [10] * 9, keys=("ar/r/pose/a", "ar/r/pose/b"))
    published = Published()
    done = play_pass(path, Pacer(10.0), published, window=Window(start_ns=25 * MS, end_ns=75 * MS),
                     select=lambda channel: channel.topic.endswith("/a"))
    assert published.seqs == [2, 3]  # positions 30 and 50 ms on key a (sequence counts per channel)
    assert done.read == 9  # the one at 80 ms, past the end of the window, ended the pass


def test_step_and_resume_from_another_thread(tmp_path):
    path = recording(tmp_path / "r.mcap", [100, 100, 100])
    pacer = Pacer(1.0, paused=True)
    published = Published()
    player = threading.Thread(target=play_pass, args=(path, pacer, published))
    player.start()
    try:
        time.sleep(0.15)
        assert published.seqs == []
        pacer.step()
        deadline = time.monotonic() + 10
        while not published.seqs and time.monotonic() < deadline:
            time.sleep(0.01)
        time.sleep(0.15)  # more than the gap to the next message: still paused
        assert published.seqs == [0]
        resumed = time.monotonic_ns()
        pacer.resume()
        player.join(2.0)
        assert published.seqs == [0, 1, 2, 3]
        gap_ms = (published.times[1] - resumed) / MS
        assert 100 <= gap_ms < 100 + STALL_MS  # the gap after the step is kept: never early, not stalled
    finally:
        pacer.stop()
        player.join(2.0)


def test_stopping_ends_a_paused_pass_at_once(tmp_path):
    path = recording(tmp_path / "r.mcap", [10])
    running = threading.Event()
    running.set()
    pacer = Pacer(1.0, paused=True, running=running.is_set)
    threading.Timer(0.1, running.clear).start()
    started = time.monotonic()
    done = play_pass(path, pacer, Published())
    assert done.stopped and done.played == 0 and time.monotonic() - started < 1.0


def test_a_pass_over_a_truncated_file_plays_the_intact_part_and_reports_the_damage(tmp_path):
    full = recording(tmp_path / "r.mcap", [1] * 19)
    data = full.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 2])
    scan = Scan(cut)
    intact = [r.message.sequence for r in scan.messages()]
    published = Published()
    done = play_pass(cut, Pacer(1.0), published)
    assert published.seqs == intact and 0 < len(intact) < 20
    assert done.damage is not None and done.damage == scan.damage and done.read == len(intact)
