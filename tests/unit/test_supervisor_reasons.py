"""What the supervisor keeps of a child's exit: its last stderr line as the reason, the restart number it
passes on, and a one-line account of a spent restart budget or of a child that cannot do its job."""

from __future__ import annotations

import json
import sys
import threading
from pathlib import Path

import pytest

from services.launcher.supervisor import ProcessSpec, Supervisor, SupervisorSettings, reason_of
from services.runtime.restarts import RESTART_ENV


def _child(name: str, code: str, restart: bool = True) -> ProcessSpec:
    return ProcessSpec(name, (sys.executable, "-c", code), restart=restart)


def _until_settled(supervisor: Supervisor) -> None:
    stop = threading.Event()
    supervisor.run(stop, poll_s=0.01)


@pytest.mark.integration
def test_the_last_stderr_line_is_the_reason_a_child_exited(capfd):
    code = "import sys; print('starting', file=sys.stderr); print('no camera 7', file=sys.stderr); sys.exit(2)"
    supervisor = Supervisor([_child("cam", code, restart=False)])
    supervisor.start()
    _until_settled(supervisor)
    (health,) = supervisor.health()
    assert (health.exit_code, health.reason) == (2, "no camera 7")
    assert "starting\nno camera 7\n" in capfd.readouterr().err  # passed on, not swallowed


@pytest.mark.integration
def test_a_zenoh_log_line_after_the_childs_own_is_passed_on_but_is_not_the_reason(capfd):
    zenoh_line = "\\x1b[2m2026-11-26T23:12Z\\x1b[0m \\x1b[31mERROR\\x1b[0m zenoh::net::protocol::gossip: unknown link"
    code = f"import sys; print('no camera 7', file=sys.stderr); print('{zenoh_line}', file=sys.stderr); sys.exit(2)"
    supervisor = Supervisor([_child("cam", code, restart=False)])
    supervisor.start()
    _until_settled(supervisor)
    (health,) = supervisor.health()
    assert (health.exit_code, health.reason) == (2, "no camera 7")
    assert "unknown link" in capfd.readouterr().err


def test_log_lines_are_reduced_to_their_message():
    text = "2026-11-25 11:14:56,085 ERROR [rec-a] artrack.recorder: node rec-a: x.mcap exists: choose another name"
    assert reason_of(text) == "node rec-a: x.mcap exists: choose another name"
    entry = {"time": "t", "level": "error", "message": "node rec-a failed",
             "exception": "Traceback (most recent call last):\n  ...\nPermissionError: [Errno 13] denied: 'x'"}
    assert reason_of(json.dumps(entry)) == "node rec-a failed: PermissionError: [Errno 13] denied: 'x'"
    assert reason_of("plain words") == "plain words"


@pytest.mark.integration
def test_children_learn_their_restart_number_and_a_spent_budget_says_the_cause_was_the_same(tmp_path: Path):
    seen = tmp_path / "restarts"
    code = (f"import os, sys; open({str(seen)!r}, 'a').write(os.environ[{RESTART_ENV!r}] + ' '); "
            "print('disk full', file=sys.stderr); sys.exit(1)")
    settings = SupervisorSettings(backoff_s=0.01, max_backoff_s=0.01, max_restarts=2)
    supervisor = Supervisor([_child("rec", code)], settings)
    supervisor.start()
    _until_settled(supervisor)
    assert seen.read_text().split() == ["0", "1", "2"]
    assert supervisor.failure("rec") == ("it exited 3 times within 60 s, more than its restart budget (2 restarts) "
                                         "allows; each time: disk full")


@pytest.mark.integration
def test_a_child_that_cannot_do_its_job_is_failed_at_once_and_says_why(tmp_path: Path):
    seen = tmp_path / "starts"
    code = (f"import sys; open({str(seen)!r}, 'a').write('start '); "
            "print('node cam: no camera 7', file=sys.stderr); sys.exit(2)")
    settings = SupervisorSettings(backoff_s=0.01, max_backoff_s=0.01, max_restarts=5)
    supervisor = Supervisor([_child("cam", code)], settings)
    supervisor.start()
    _until_settled(supervisor)
    (health,) = supervisor.health()
    assert (health.state, health.restarts, health.exit_code) == ("failed", 0, 2)
    assert seen.read_text().split() == ["start"]
    assert supervisor.failure("cam") == ("it cannot do its job (exit code 2, not restarted: it would fail alike): "
                                         "no camera 7")


@pytest.mark.integration
def test_a_killed_child_is_said_to_be_killed_whatever_it_wrote_last():
    code = "import os, signal, sys; print('recording', file=sys.stderr, flush=True); os.kill(os.getpid(), 9)"
    supervisor = Supervisor([_child("rec", code, restart=False)])
    supervisor.start()
    _until_settled(supervisor)
    assert supervisor.health()[0].reason == "killed by SIGKILL"
