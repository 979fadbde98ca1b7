"""A job's processes at the priority and on the CPUs their nodes ask for, restarted alike; a priority the user may
not give refused at once."""

from __future__ import annotations

import os
import shutil
import signal
import sys
import time
from pathlib import Path

import pytest

from services.launcher.scheduling import Scheduling, may_raise_priority
from services.launcher.supervisor import ProcessSpec, Supervisor
from tests.integration.support import START_S, wait_until

pytestmark = pytest.mark.integration


def supervised(specs: list[ProcessSpec]) -> Supervisor:
    """A supervisor of ``specs`` run until every child has finished or failed (30 s at most), then stopped."""
    supervisor = Supervisor(specs)
    supervisor.start()
    try:
        deadline = time.monotonic() + 30.0
        while supervisor.step() and time.monotonic() < deadline:
            time.sleep(0.05)
    finally:
        supervisor.stop()
    return supervisor


def test_each_child_starts_at_its_priority_on_its_cpus(tmp_path):
    cpu = max(os.sched_getaffinity(0))
    shown = tmp_path / "shown.txt"
    code = (f"import os; open({str(shown)!r}, 'w').write(f'{{os.getpriority(os.PRIO_PROCESS, 0)}} "
            f"{{sorted(os.sched_getaffinity(0))}}')")
    supervised([ProcessSpec("child", (sys.executable, "-c", code), restart=False, scheduling=Scheduling(13, (cpu,)))])
    assert shown.read_text() == f"13 [{cpu}]"


def children(pid: int) -> dict[str, int]:
    """``{process name: pid}`` of the node and group processes ``pid`` started."""
    found = {}
    for task in Path(f"/proc/{pid}/task").iterdir():
        for child in (task / "children").read_text().split():
            argv = Path(f"/proc/{child}/cmdline").read_bytes().split(b"\0")
            if b"services.cli" in argv and (b"node" in argv or b"group" in argv):
                name = argv[argv.index(b"--name") + 1] if b"--name" in argv else argv[argv.index(b"group") + 1]
                found[name.decode()] = int(child)
    return found


def threads(pid: int) -> list[tuple[int, str]]:
    """``(nice, allowed CPUs)`` of every thread of process ``pid`` (nice as the kernel reports it)."""
    found = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        nice = int((task / "stat").read_text().rsplit(")", 1)[1].split()[16])
        cpus = next(line.split()[1] for line in (task / "status").read_text().splitlines()
                    if line.startswith("Cpus_allowed_list"))
        found.append((nice, cpus))
    return found


def test_a_job_runs_each_process_as_its_nodes_ask_and_restarts_it_alike(procs, tmp_path):
    own = os.getpriority(os.PRIO_PROCESS, 0)
    cpu = max(os.sched_getaffinity(0))
    job = procs.artrack("run", "stereo", "--source", "synthetic:ir_rig", "--fps", "30", "--flow", "realtime",
                        "--nice", str(min(own + 2, 19)), "--nice", f"bodies={min(own + 1, 19)}",
                        "--cpus", f"bodies={cpu}", "--record", str(tmp_path / "run.mcap"), name="job")
    wait_until(lambda: "node capture (capture) up" in job.stderr, 6 * START_S,
               "the job's source to be up (it starts last)")
    pids = children(job.pid)
    assert set(pids) == {"rig", "bodies", "recorder"}, pids
    assert f"started bodies (pid {pids['bodies']}, nice {min(own + 1, 19)}, CPUs [{cpu}])" in job.stderr, job.stderr
    assert {nice for nice, _ in threads(pids["rig"])} >= {min(own + 2, 19)}, threads(pids["rig"])
    assert all(cpus == f"{cpu}" for _, cpus in threads(pids["bodies"])), threads(pids["bodies"])
    assert int(Path(f"/proc/{pids['bodies']}/stat").read_text().rsplit(")", 1)[1].split()[16]) == min(own + 1, 19)
    recorder = Path(f"/proc/{pids['recorder']}/stat").read_text().rsplit(")", 1)[1].split()[16]
    assert int(recorder) == own, "a sink keeps the launcher's priority when no node is named"

    os.kill(pids["bodies"], signal.SIGKILL)
    wait_until(lambda: children(job.pid).get("bodies", pids["bodies"]) != pids["bodies"], 3 * START_S,
               "the bodies process to be restarted")
    again = children(job.pid)["bodies"]
    wait_until(lambda: len(threads(again)) > 1, 3 * START_S, "the restarted process to make its threads")
    assert all(cpus == f"{cpu}" for _, cpus in threads(again)), threads(again)
    assert int(Path(f"/proc/{again}/stat").read_text().rsplit(")", 1)[1].split()[16]) == min(own + 1, 19)
    os.killpg(job.pid, signal.SIGINT)
    assert job.wait(3 * START_S) == 0, job.describe()  # Ctrl-C is how a job of a live source ends


def test_a_priority_this_user_may_not_give_is_refused_before_anything_starts(procs, tmp_path):
    own = os.getpriority(os.PRIO_PROCESS, 0)
    if own <= -20:
        pytest.skip("this process already runs at the highest priority")
    prefix: list[str] = []
    if may_raise_priority(own - 1):
        setpriv = shutil.which("setpriv")
        if os.geteuid() != 0 or setpriv is None:
            pytest.skip("this user may raise priorities, and setpriv is not there to run the job without that right")
        prefix = [setpriv, "--bounding-set=-sys_nice", "--inh-caps=-sys_nice"]
    job = procs.start([*prefix, sys.executable, "-m", "services.cli", "run", "marker", "--source", "synthetic:markers",
                       "--frames", "10", "--nice", f"marker-cam0={own - 1}"], name="refused")
    assert job.wait(3 * START_S) == 2, job.describe()
    errors = [line for line in job.stderr.splitlines() if "ERROR" in line]
    assert len(errors) == 1 and errors[0].endswith(
        f"job: nodes.marker-cam0.nice {own - 1}: a priority above this process's (nice {own}) needs the CAP_SYS_NICE "
        f"capability or a nice limit that allows it (`ulimit -e`, systemd's LimitNICE=); this user has neither: give "
        f"nice {own} or more"), job.stderr
    assert "started" not in job.stderr, "a process was started before the refusal"


def test_a_process_that_cannot_be_given_its_cpus_is_failed_and_the_others_go_on(tmp_path):
    missing = max(os.sched_getaffinity(0)) + 64
    done = tmp_path / "done.txt"
    supervisor = supervised([
        ProcessSpec("pinned", (sys.executable, "-c", "pass"), scheduling=Scheduling(None, (missing,))),
        ProcessSpec("other", (sys.executable, "-c", f"open({str(done)!r}, 'w').write('ran')"), restart=False)])
    health = {child.name: child for child in supervisor.health()}
    assert health["pinned"].state == "failed" and health["pinned"].exit_code == 2
    why = supervisor.failure("pinned")
    assert why.endswith(f"its process could not be given CPUs [{missing}]: this machine does not allow it now"), why
    assert done.read_text() == "ran" and health["other"].state != "failed"
