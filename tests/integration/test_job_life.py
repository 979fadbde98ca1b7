"""The life of an ``artrack run`` job: a node that cannot start, a killed recorder, a crash loop, a node
that cannot do its job once frames come, a damaged recording as source, Ctrl-C, and ``artrack status`` on a
running job."""

import os
import shutil
import signal

import pytest

from protocol import decode
from services.launcher.status import gather
from services.recorder.info import summarise
from services.recorder.reading import Scan
from tests.integration.support import ROOT, START_S, states, wait_until

pytestmark = pytest.mark.integration

ENDLESS = 100_000
"""Frames of a finite source that outlives every test."""


def _pid(session, keys, name: str, not_pid: int | None = None) -> int:
    """The pid node ``name`` of this rig states, once it states one other than ``not_pid``."""

    def probe() -> int | None:
        stats = states(session, keys).get(name)
        return stats.pid if stats is not None and stats.pid != not_pid else None

    return wait_until(probe, 2 * START_S, f"node {name} to state a pid other than {not_pid}")


def test_a_node_that_cannot_start_ends_the_job_at_once_with_its_one_line_reason(procs, tmp_path):
    """Two recorders of one file both pass the check before start; the second to start is refused by the first's
    file, and the job ends with its reason instead of waiting for it to come up."""
    out = tmp_path / "twice.mcap"
    path = tmp_path / "twice.toml"
    path.write_text(f'[nodes.cam]\nkind = "capture"\nsource = ["synthetic:pattern"]\nframes = {ENDLESS}\nfps = 5\n'
                    'scene = { width = 64, height = 64 }\n\n'
                    f'[nodes.rec-a]\nkind = "recorder"\nout = "{out}"\n\n'
                    f'[nodes.rec-b]\nkind = "recorder"\nout = "{out}"\n')
    job = procs.artrack("run", str(path), name="job")
    assert job.wait(START_S) == 2, job.describe()
    last = [line for line in job.stderr.splitlines() if line.strip()][-1]
    assert "could not start: " in last and "twice.mcap" in last and "exists" in last, job.describe()
    assert "did not come up" not in job.stderr


def test_a_source_that_cannot_start_ends_the_job_with_code_2(procs, tmp_path):
    job = procs.artrack("run", "echo", "--source", f"images:{tmp_path}", name="job")
    assert job.wait(2 * START_S) == 2, job.describe()
    assert "source capture ended with code 2" in job.stderr


@pytest.mark.parametrize("scheme", ["images", "video"])
def test_a_source_that_sends_no_frame_is_an_error_in_one_line_with_code_2(procs, tmp_path, scheme):
    """A folder of files that are not images, a file OpenCV opens but cannot decode: nothing to track."""
    for name in ("a.png", "b.png"):
        (tmp_path / name).write_bytes(b"not an image")
    uri = f"images:{tmp_path}" if scheme == "images" else f"video:{tmp_path / 'a.png'}"
    job = procs.artrack("run", "echo", "--source", uri, name="job")
    assert job.wait(2 * START_S) == 2, job.describe()
    last = [line for line in job.stderr.splitlines() if line.strip()][-1]
    assert last.endswith(f"{uri}: no frame could be read, none was sent"), job.describe()
    assert "runs until Ctrl-C" not in job.stderr


def test_a_damaged_recording_as_source_plays_to_the_damage_and_ends_with_code_3(procs, tmp_path):
    damaged = tmp_path / "cut.mcap"
    shutil.copyfile(ROOT / "recordings" / "pattern.mcap", damaged)
    with open(damaged, "r+b") as f:
        f.truncate(damaged.stat().st_size * 2 // 3)
    assert summarise(damaged).damage is not None
    job = procs.artrack("run", "echo", "--source", f"recording:{damaged}", name="job")
    assert job.wait(3 * START_S) == 3, job.describe()


def test_status_sees_a_running_job_and_ctrl_c_before_its_source_ended_is_130(procs, session, bus):
    job = procs.artrack("run", "echo", "--source", "synthetic:pattern", "--frames", str(ENDLESS), "--fps", "5",
                        name="job")

    def healthy():
        assert job.poll() is None, job.describe()
        status = gather(session, bus.keys, 1.0)
        nodes = {node.name for health in status.pipelines.values() for node in health.nodes}
        return status if nodes == {"capture", "echo-cam0"} and not status.problems() else None

    status = wait_until(healthy, 2 * START_S, "the job to answer healthy")
    assert [health.pipeline for health in status.pipelines.values()] == ["artrack run echo"]
    check = procs.run("status", "--check")
    assert check.poll() == 0, check.describe()
    os.kill(job.pid, signal.SIGINT)
    assert job.wait(START_S) == 130, job.describe()


def test_a_node_that_keeps_dying_spends_its_restart_budget_and_ends_the_job(procs, session, bus, tmp_path):
    path = tmp_path / "loop.toml"
    path.write_text('[supervisor]\nmax_restarts = 1\nbackoff_s = 0.1\n\n'
                    f'[nodes.cam]\nkind = "capture"\nsource = ["synthetic:pattern"]\nframes = {ENDLESS}\nfps = 5\n'
                    'scene = { width = 64, height = 64 }\n\n[nodes.echo]\nkind = "echo"\ncamera = "cam0"\n')
    job = procs.artrack("run", str(path), name="job")
    _pid(session, bus.keys, "cam")  # the source starts once the job has seen the others up
    first = _pid(session, bus.keys, "echo")
    os.kill(first, signal.SIGKILL)
    os.kill(_pid(session, bus.keys, "echo", not_pid=first), signal.SIGKILL)
    assert job.wait(START_S) == 1, job.describe()
    last = [line for line in job.stderr.splitlines() if line.strip()][-1]
    assert "node echo failed: it exited 2 times" in last and "each time: killed by SIGKILL" in last, job.describe()


def test_a_node_that_cannot_do_its_job_is_not_restarted_and_ends_the_job_with_its_reason(procs, tmp_path):
    """A node that stops with a NodeError once frames come (exit 2) would fail alike however often it
    started: it is left down, and the job ends at once with code 1 and the node's one line."""
    path = tmp_path / "give_up.toml"
    path.write_text(f'[nodes.cam]\nkind = "capture"\nsource = ["synthetic:pattern"]\nframes = {ENDLESS}\nfps = 5\n'
                    'scene = { width = 96, height = 64 }\n\n[nodes.give-up]\nkind = "give_up"\ncamera = "cam0"\n')
    job = procs.artrack("run", str(path), name="job", env={"ARTRACK_PLUGINS": "tests.plugin_tracker"})
    assert job.wait(START_S) == 1, job.describe()
    last = [line for line in job.stderr.splitlines() if line.strip()][-1]
    assert last.endswith("node give-up failed: it cannot do its job (exit code 2, not restarted: it would fail "
                         "alike): cam0 sends 96x64 frames, which this node cannot use"), job.describe()
    assert "restarting" not in job.stderr and job.stderr.count("started give-up") == 1, job.describe()


def test_a_killed_recorder_goes_on_in_a_new_part_and_info_lists_the_parts(procs, session, bus, tmp_path):
    out = tmp_path / "run.mcap"
    job = procs.artrack("run", "echo", "--source", "synthetic:pattern", "--frames", "60", "--fps", "10",
                        "--record", str(out), name="job")
    _pid(session, bus.keys, "capture")  # the source starts once the job has seen the others up
    recorder = _pid(session, bus.keys, "recorder")
    wait_until(lambda: out.exists() and summarise(out).messages > 20, 2 * START_S, "the recorder to flush")
    os.kill(recorder, signal.SIGKILL)
    assert job.wait(3 * START_S) == 0, job.describe()
    last = job.stderr.strip().splitlines()[-1]
    assert last.strip() == "frames lost: restarted (the frames they held are lost) recorder 1x", job.describe()

    second = tmp_path / "run.part2.mcap"
    assert sorted(p.name for p in tmp_path.glob("*.mcap")) == ["run.mcap", "run.part2.mcap"]
    killed, went_on = summarise(out), summarise(second)
    assert killed.damage is not None and killed.messages > 20  # readable up to the kill
    assert went_on.damage is None and went_on.messages > 0
    assert went_on.metadata["artrack.recording"]["continues"] == "run.mcap"
    assert killed.parts == [str(out), str(second)]

    def image_seqs(path):
        return [decode(m.message.data).header.seq for m in Scan(path).messages()
                if m.channel.topic.endswith("/cam0/image")]

    before, after = image_seqs(out), image_seqs(second)
    assert before and after and max(before) < min(after)
    info = procs.run("info", str(out))
    assert info.poll() == 3, info.describe()
    assert "parts      run.mcap, run.part2.mcap" in info.stdout
