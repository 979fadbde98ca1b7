"""What a job says while it runs and at its end: frame totals, rates, the newest statistics, lateness."""

import io
import threading
import time

import cv2
import numpy as np
import pytest

from protocol.message import Header
from protocol.system import NodeStats, StreamStats, SyncInputStats, SyncStats
from services.capture.node import LATE_S, _Lateness, _Pacer
from services.launcher.pipeline import NodeSpec
from services.launcher.progress import (
    Display,
    JobFigures,
    _drop_advice,
    _drop_detail,
    delivered_rate,
    frames_expected,
    frames_sent,
)
from services.runtime.pacing import wait_until


def _stats(node: str, stamp_ns: int, sent: int = 0) -> NodeStats:
    streams = (StreamStats(key="ar/rig0/cam0/camera_info", direction="out", messages=sent + 1),
               StreamStats(key="ar/rig0/cam0/image", direction="out", messages=sent))
    return NodeStats(header=Header(stamp_ns=stamp_ns), node=node, kind="capture", host="h", pid=1, uptime_s=1.0,
                     streams=streams)


def test_a_capture_knows_its_total_from_frames_a_folder_or_a_video_and_none_when_endless(tmp_path):
    folder = tmp_path / "frames"
    folder.mkdir()
    for i in range(7):
        cv2.imwrite(str(folder / f"{i:03d}.png"), np.zeros((8, 8), np.uint8))
    (folder / "notes.txt").write_text("not an image")
    video = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 10, (32, 24))
    for _ in range(9):
        writer.write(np.zeros((24, 32, 3), np.uint8))
    writer.release()

    def capture(**params) -> int | None:
        return frames_expected(NodeSpec(kind="capture", **params))

    assert capture(source=["synthetic:markers"], frames=600) == 600
    assert capture(source=["synthetic:markers"]) is None
    assert capture(source=["camera:0"]) is None
    assert capture(source=[f"images:{folder}"]) == 7
    assert capture(source=[f"images:{folder}"], frames=5) == 5
    assert capture(source=[f"images:{folder}"], frames=50) == 7
    assert capture(source=[f"images:{folder}"], loop=True) is None
    assert capture(source=[f"video:{video}"]) == 9
    assert capture(source=[f"video:{video}", f"images:{folder}"]) == 7  # a rig ends with its shortest source


def test_frames_sent_are_the_image_messages_not_the_other_streams():
    assert frames_sent(_stats("capture", 1, sent=12)) == 12


def test_the_drops_of_a_node_are_told_per_input_and_per_latest_wins_join():
    """A bodies node drops the sets of blobs it could not follow (a latest-wins join) and an input its frames."""
    inputs = (SyncInputStats(name="cam0", key="ar/r/cam0/blobs", received=100, joined=100),
              SyncInputStats(name="cam1", key="ar/r/cam1/blobs", received=100, joined=100))
    stats = NodeStats(header=Header(stamp_ns=1), node="bodies", kind="rigid_bodies", host="h", pid=1, uptime_s=1.0,
                      dropped=9, streams=(StreamStats(key="ar/r/cam0/camera_info", direction="in", messages=50,
                                                      dropped=2),),
                      synced=(SyncStats(by="seq", sets=100, dropped=7, inputs=inputs),))
    assert _drop_detail(stats) == "2 of 50 on ar/r/cam0/camera_info, 7 of 100 sets of ar/r/cam0/blobs + ar/r/cam1/blobs"


def test_the_advice_on_drops_names_the_queue_a_node_kind_has():
    assert _drop_advice("marker_pose").endswith("queue more of them (--depth N)")
    assert _drop_advice("rigid_bodies").endswith("queue more of them (--backlog N)")
    assert _drop_advice("viewer") == "for every frame, ask a lower --fps"


def test_the_newest_statistics_of_a_node_win_whatever_order_they_come_in():
    figures = JobFigures()
    figures.update(_stats("capture", 2_000, sent=20), source="capture")
    figures.update(_stats("capture", 1_000, sent=10), source="capture")  # an older answer, late
    assert frames_sent(figures.stats["capture"]) == 20
    assert figures.samples == [(2_000, 20)]


def test_the_delivered_rate_comes_from_the_first_and_last_posed_frames():
    figures = JobFigures()
    for seq in (5, 0, 299, 100):  # in any order, repeated frames and all
        figures.posed(seq, 1_000_000_000 + seq * 10_000_000)  # 100 frames a second
    figures.posed(299, 4_000_000_000)
    assert delivered_rate(figures, from_poses=True) == pytest.approx(100.0)


def test_poses_that_came_in_a_burst_faster_than_the_rate_asked_do_not_time_the_source():
    """The poses of 60 frames reached the job 1.3 ms apart end to end (its threads held up on a busy machine):
    no source sends 44 000 frames a second when 1 000 were asked, so the rate comes from the source's own
    statistics, or is not told."""
    figures = JobFigures()
    figures.posed(0, 5_000_000_000)
    figures.posed(59, 5_001_300_000)
    assert delivered_rate(figures, from_poses=True) == pytest.approx(59 / 0.0013)  # nothing asked to hold it to
    assert delivered_rate(figures, from_poses=True, asked=1000.0) is None
    for stamp_s, sent in ((0.0, 0), (0.5, 100), (1.0, 200), (1.5, 300)):
        figures.update(_stats("capture", int(stamp_s * 1e9) + 1, sent), source="capture")
    assert delivered_rate(figures, from_poses=True, asked=1000.0) == pytest.approx(200.0)
    assert delivered_rate(figures, from_poses=True, asked=50_000.0) == pytest.approx(59 / 0.0013)


def test_a_lossless_run_has_its_rate_from_statistics_short_of_the_final_count():
    figures = JobFigures()
    figures.posed(0, 0)
    figures.posed(10, 1)  # the pace of the slowest node, not the source's
    for stamp_s, sent in ((0.0, 0), (0.5, 50), (1.0, 150), (1.5, 250), (2.0, 300), (2.5, 300)):
        figures.update(_stats("capture", int(stamp_s * 1e9) + 1, sent), source="capture")
    assert delivered_rate(figures, from_poses=False) == pytest.approx(200.0)


def test_a_run_too_short_to_measure_gives_no_rate():
    figures = JobFigures()
    figures.update(_stats("capture", 1, 0), source="capture")
    figures.update(_stats("capture", 2, 30), source="capture")
    assert delivered_rate(figures, from_poses=True) is None


class _Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


@pytest.mark.parametrize(("out", "progress", "quiet", "shown"), [
    (io.StringIO(), "auto", False, (False, True)),
    (_Terminal(), "auto", False, (True, True)),
    (io.StringIO(), "on", False, (True, True)),
    (_Terminal(), "off", False, (False, True)),
    (_Terminal(), "on", True, (False, False)),
])
def test_progress_shows_on_a_terminal_or_when_asked_and_quiet_silences_both(out, progress, quiet, shown):
    display = Display.choose(progress, quiet, out)
    assert (display.progress, display.summary) == shown


class _Node:
    """What ``_Lateness`` and ``_Pacer`` use of a node: its reports, its log and its wait."""

    def __init__(self):
        self.reports: list[tuple[str, str, str, int]] = []
        self.logged: list[str] = []
        self.log = self

    def report(self, kind: str, detail: str, key: str = "", count: int = 1) -> None:
        self.reports.append((kind, detail, key, count))

    def warning(self, message: str, *args) -> None:
        self.logged.append(message % args)

    info = warning

    def wait_until(self, due: float) -> bool:
        return wait_until(due, threading.Event())


def test_a_pacer_asked_more_than_its_source_gives_says_how_late_each_frame_is():
    node = _Node()
    pacer = _Pacer(lambda: 1000.0)
    behind = []
    for _ in range(5):
        behind.append(pacer.wait_for(node, None, untimed=False))
        time.sleep(0.03)  # a source that takes 30 ms a frame, asked for one every 1 ms
    assert behind[0] == 0.0
    assert all(b > LATE_S for b in behind[2:]), behind


def test_late_frames_are_counted_reported_at_the_first_and_summed_up_at_the_end():
    node = _Node()
    late = _Lateness(node, "ar/rig0/cam0/image")
    late.count(0.0, 1000.0)
    for _ in range(9):
        late.count(0.2, 1000.0)
    late.end(10, 1000.0)
    assert [r[3] for r in node.reports] == [1, 8]  # the first at once, the rest with the end
    assert sum(r[3] for r in node.reports) == 9
    assert all(r[0] == "late" and r[2] == "ar/rig0/cam0/image" for r in node.reports)
    assert "9 of 10 frames late" in node.reports[-1][1] and "of the 1000 asked" in node.reports[-1][1]
    assert any("9 of 10 frames late" in line for line in node.logged)  # the node would not log it this soon


def test_a_source_on_time_reports_nothing_late():
    node = _Node()
    late = _Lateness(node, "ar/rig0/cam0/image")
    for _ in range(5):
        late.count(0.001, 30.0)
    late.end(5, 30.0)
    assert node.reports == []
    assert len(node.logged) == 1 and "5 frames sent" in node.logged[0]
