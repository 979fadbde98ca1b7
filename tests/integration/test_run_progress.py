"""What ``artrack run`` says on standard error: a progress line when asked (or on a terminal), a summary at
the end that agrees with what the job recorded, one line for a source with no end, nothing with --quiet."""

from __future__ import annotations

import re
import signal
from collections import Counter

import pytest

from tests.integration.support import START_S, wait_until
from tests.integration.test_marker_pipeline import recorded

pytestmark = pytest.mark.integration

PATTERN = ("--source", "synthetic:pattern", "--scene-option", "width=64", "--scene-option", "height=64")


def summary_of(stderr: str) -> list[str]:
    """The lines of the job summary (from its heading on, log lines of the nodes left out)."""
    assert "job summary (" in stderr, stderr
    lines = stderr[stderr.index("job summary ("):].splitlines()
    return [line for line in lines if not re.match(r"\d{4}-\d\d-\d\d ", line)]


def table(lines: list[str], heading: str) -> dict[str, dict[str, str]]:
    """The rows of the summary table whose first column is ``heading``, by that column, as {column: cell}."""
    start = next(i for i, line in enumerate(lines) if line.split()[:1] == [heading])
    columns = lines[start].split()
    rows = {}
    for line in lines[start + 1:]:
        if not line.startswith("    "):
            break
        cells = line.split(None, len(columns) - 1)
        rows[cells[0]] = dict(zip(columns, cells, strict=True))
    return rows


def test_a_real_time_job_too_fast_for_its_source_says_so_and_its_summary_matches_the_recording(procs, tmp_path):
    out = tmp_path / "job.mcap"
    job = procs.artrack("run", "marker", "--source", "synthetic:markers", "--frames", "60", "--fps", "1000",
                        "--flow", "realtime", "--marker-length", "0.05", "--record", str(out), name="job")
    assert job.wait(4 * START_S) == 0, job.describe()
    assert job.stdout == ""  # standard output stays for data
    assert "\x1b[K" not in job.stderr  # not a terminal: no progress line
    lines = summary_of(job.stderr)
    source = next(line for line in lines if line.strip().startswith("source capture:"))
    # The rate, timed by the poses' arrival, is left out when they came in a burst (a busy machine): never above
    # the rate asked.
    assert "source capture: 60 of 60 frames sent" in source, source
    rate = re.search(r"60 of 60 frames sent, at ([\d.]+) fps of the 1000 asked", source)
    assert rate is None or 0 < float(rate.group(1)) < 1000, source
    assert "the source could not keep the pace asked" in source

    nodes = table(lines, "NODE")
    assert set(nodes) == {"capture", "marker-cam0", "recorder"}
    late = re.search(r"late (\d+)", nodes["capture"]["SKIPPED"])
    assert late and int(late.group(1)) > 0 and f"; {late.group(1)} late" in source
    assert "the source cannot keep up with the 1000 fps asked" in job.stderr  # the node's own warning
    assert f"{late.group(1)} of 60 frames late: the source delivered" in job.stderr

    messages = recorded(out)
    pose_keys = {key: ms for key, ms in messages.items() if "/pose/" in key}
    expected = {key.split("/pose/", 1)[1]: Counter(p.state.value for p in ms) for key, ms in pose_keys.items()}
    poses = table(lines, "TARGET")
    assert set(poses) == set(expected) and expected
    for target, counts in expected.items():
        assert int(poses[target]["POSES"]) == sum(counts.values())
        assert int(poses[target]["TRACKING"]) == counts["tracking"]

    # Real-time frames go out latest-wins (Zenoh's congestion control DROP): on a busy machine the transport may
    # drop one, and the recorder counts it as missing. Every frame is in the file or in those counts.
    images = sum(len(ms) for key, ms in messages.items() if key.endswith("/cam0/image"))
    assert int(nodes["capture"]["OUT"]) >= 60
    assert images + int(nodes["recorder"]["MISSING"]) + int(nodes["recorder"]["DROPPED"]) == 60, nodes["recorder"]
    dropped = int(nodes["marker-cam0"]["DROPPED"])
    advice = [line for line in lines if line.strip().startswith("marker-cam0 dropped")]
    assert bool(advice) == (dropped > 0), lines
    if dropped:
        assert f"marker-cam0 dropped {dropped} of " in advice[0] and "--depth N" in advice[0]
    assert f"recording: {out}" in lines[-2]
    losses = {(name, column): int(row[column]) for name, row in nodes.items() for column in ("DROPPED", "MISSING")
              if int(row[column])}
    if not losses:
        assert lines[-1].strip().startswith("every frame accounted for"), lines[-1]
    else:
        assert lines[-1].strip().startswith("frames lost: "), lines[-1]
        assert all(f"{name} {count}" in lines[-1] for (name, _), count in losses.items()), (losses, lines[-1])


def test_a_lossless_job_takes_every_frame_sends_none_late_and_says_every_frame_is_accounted_for(procs, tmp_path):
    out = tmp_path / "job.mcap"
    job = procs.artrack("run", "marker", "--source", "synthetic:markers", "--frames", "60", "--fps", "1000",
                        "--marker-length", "0.05", "--record", str(out), "--strict", name="job")
    assert job.wait(4 * START_S) == 0, job.describe()
    lines = summary_of(job.stderr)
    source = next(line for line in lines if line.strip().startswith("source capture:"))
    assert "60 of 60 frames sent" in source and "late" not in source, source
    nodes = table(lines, "NODE")
    assert (nodes["marker-cam0"]["IN"], nodes["marker-cam0"]["DONE"]) == ("120", "60")  # images and calibration
    assert all(row["DROPPED"] == row["MISSING"] == "0" for row in nodes.values()), nodes
    assert len(recorded(out)[next(key for key in recorded(out) if key.endswith("/cam0/image"))]) == 60
    assert lines[-1].strip() == "every frame accounted for: no node dropped a frame or missed one"


def test_progress_on_redraws_one_line_with_the_frame_total(procs):
    job = procs.artrack("run", "capture", *PATTERN, "--frames", "20", "--fps", "20", "--progress", "on", name="job")
    assert job.wait(3 * START_S) == 0, job.describe()
    raw = job.err_path.read_bytes().decode()  # as written: reading text would turn each \r into a new line
    drawn = re.findall(r"\x1b\[K(frames [^\r\n]*)\r", raw)
    assert drawn, job.stderr
    assert all(re.match(r"frames \d+/20 ", line) for line in drawn), drawn
    assert "frames 20/20 " in drawn[-1]
    assert "source capture: 20 of 20 frames sent" in job.stderr


def test_quiet_says_neither_progress_nor_summary(procs):
    job = procs.artrack("run", "capture", *PATTERN, "--frames", "5", "--fps", "20", "--progress", "on", "--quiet",
                        name="job")
    assert job.wait(3 * START_S) == 0, job.describe()
    assert "job summary" not in job.stderr and "\x1b[K" not in job.err_path.read_bytes().decode(), job.stderr
    assert "5 frames sent at" in job.stderr  # the nodes' own log lines are not the job's to silence


def test_a_live_source_says_it_runs_until_ctrl_c_and_sums_up_when_stopped(procs):
    job = procs.artrack("run", "capture", *PATTERN, "--fps", "20", "--progress", "on", name="job")
    wait_until(lambda: job.poll() is None and "live source (capture): runs until Ctrl-C" in job.stderr, START_S,
               "the live source line")
    wait_until(lambda: re.search(r"frames [1-9]\d* ", job.stderr), 2 * START_S, "frames to flow")
    job.popen.send_signal(signal.SIGINT)
    assert job.wait(START_S) in (0, 130), job.describe()
    source = next(line for line in summary_of(job.stderr) if "source capture:" in line)
    sent = re.search(r"source capture: (\d+) frames sent", source)  # no total: the source had no end
    assert sent and int(sent.group(1)) > 0, source
