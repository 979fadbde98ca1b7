"""SLAM's mapping process lives and ends with the process that started it: a Ctrl-C on a running
``artrack run slam`` stops it cleanly, a tracker killed outright does not leave it behind, and a job whose
source fails at once ends it without a word of its own."""

from __future__ import annotations

import os
import signal
import sys
import time
from pathlib import Path

import pytest

from tests.integration.support import START_S, wait_until

pytestmark = pytest.mark.integration

MAPPING_MARK = "--multiprocessing-fork"
"""In the command line of every process Python's multiprocessing spawns (the mapping process among them)."""


def _parents() -> dict[int, int]:
    """pid -> parent pid of every process (zombies left out)."""
    parents = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except (OSError, IndexError):
            continue
        if fields[0] != "Z":
            parents[int(stat.parent.name)] = int(fields[1])
    return parents


def _spawned_under(root: int) -> list[int]:
    """The live processes below ``root`` that multiprocessing spawned."""
    parents = _parents()
    found = []
    for pid in parents:
        ancestor = parents.get(pid)
        while ancestor not in (None, 0, 1, root):
            ancestor = parents.get(ancestor)
        if ancestor == root:
            try:
                if MAPPING_MARK in Path(f"/proc/{pid}/cmdline").read_bytes().decode(errors="replace"):
                    found.append(pid)
            except OSError:
                continue
    return found


def _alive(pids: list[int]) -> list[int]:
    return [pid for pid in pids if pid in _parents()]


def test_ctrl_c_on_a_slam_job_ends_its_mapping_process_cleanly(procs):
    job = procs.artrack("run", "slam", "--source", "synthetic:room", "--frames", "100000", "--fps", "10",
                        name="job")
    children = wait_until(lambda: job.poll() is None and _spawned_under(job.pid), 3 * START_S,
                          "the SLAM node's mapping process to start")
    time.sleep(2.0)  # frames tracked and keyframes mapped by then
    os.killpg(job.pid, signal.SIGINT)  # as Ctrl-C does: the whole foreground group
    assert job.wait(3 * START_S) == 130, job.describe()
    assert "Traceback" not in job.stderr and "KeyboardInterrupt" not in job.stderr, job.stderr
    wait_until(lambda: not _alive(children), 5.0, f"the mapping process {children} to end")


def test_a_killed_tracker_does_not_leave_its_mapping_process_behind(procs):
    script = ("import time\n"
              "from services.synthetic import make_scene\n"
              "from services.slam.system import SlamSystem\n"
              "system = SlamSystem(make_scene('room').cameras[0], mapping='process')\n"
              "print(system._mapper._process.pid, flush=True)\n"
              "time.sleep(600)\n")
    tracker = procs.start([sys.executable, "-c", script], name="tracker")
    child = int(wait_until(lambda: tracker.stdout.strip() or tracker.poll() is not None, 3 * START_S,
                           "the mapping process's pid") or 0)
    assert child in _spawned_under(tracker.pid), tracker.describe()
    os.kill(tracker.pid, signal.SIGKILL)
    wait_until(lambda: not _alive([child]), 5.0, f"the mapping process {child} to end after its tracker")


def test_a_slam_job_whose_source_fails_at_once_ends_quietly_and_says_why(procs, tmp_path):
    """The source fails while the mapping process spawned ahead of the first map still imports pycolmap: it is
    ended without the stack trace pycolmap's signal handler prints for a SIGTERM, and the job's last line is
    the source's reason."""
    empty = tmp_path / "empty"
    empty.mkdir()
    job = procs.artrack("run", "slam", "--source", f"images:{empty}", name="job")
    assert job.wait(3 * START_S) == 2, job.describe()
    assert "stack trace" not in job.stderr and "Aborted at" not in job.stderr, job.stderr
    last = job.stderr.strip().splitlines()[-1]
    assert f"images:{empty}: no image files in {empty}" in last, last
