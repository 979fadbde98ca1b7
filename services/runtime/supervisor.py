"""Process supervision: start commands, restart the ones that die, stop them all.

A child that exits with code 0 has finished its job and is left alone. One that dies
(non-zero code or a signal) while the supervisor runs is restarted after a back-off that doubles
with each quick failure (0.5 s, 1 s, 2 s ... up to 10 s) and resets once the child has
run for ``stable_s``. Stopping sends SIGTERM to every child, waits up to ``grace_s``, then
SIGKILLs what is left and reaps everything. On Linux each child also asks the kernel for
SIGTERM should the supervisor die without stopping it, so no child outlives it.
"""

from __future__ import annotations

import ctypes
import logging
import os
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field

log = logging.getLogger(__name__)

_PR_SET_PDEATHSIG = 1


@dataclass(frozen=True)
class ProcessSpec:
    """A command to keep running: ``argv`` with ``env`` added to the supervisor's environment."""

    name: str
    argv: tuple[str, ...]
    env: dict[str, str] = field(default_factory=dict)
    restart: bool = True


@dataclass
class _Child:
    spec: ProcessSpec
    process: subprocess.Popen | None = None
    started: float = 0.0
    restarts: int = 0
    failures: int = 0
    restart_at: float | None = None
    finished: bool = False
    exit_code: int | None = None


def _die_with_parent() -> None:
    libc = ctypes.CDLL(None, use_errno=True)
    libc.prctl(_PR_SET_PDEATHSIG, signal.SIGTERM)


class Supervisor:
    """Keeps a set of processes running (see the module docstring). Call from the main thread."""

    def __init__(self, specs: list[ProcessSpec], *, backoff_s: float = 0.5, max_backoff_s: float = 10.0,
                 stable_s: float = 10.0, grace_s: float = 1.5):
        self.backoff_s = backoff_s
        self.max_backoff_s = max_backoff_s
        self.stable_s = stable_s
        self.grace_s = grace_s
        self._children = {spec.name: _Child(spec) for spec in specs}

    def pids(self) -> dict[str, int]:
        """Pid of every child that is running now."""
        return {name: c.process.pid for name, c in self._children.items() if c.process and c.process.poll() is None}

    def exit_codes(self) -> dict[str, int | None]:
        """The code each child last exited with (None while it never has)."""
        return {name: c.exit_code for name, c in self._children.items()}

    def restarts(self) -> dict[str, int]:
        return {name: c.restarts for name, c in self._children.items()}

    def start(self) -> None:
        for child in self._children.values():
            self._spawn(child)

    def _spawn(self, child: _Child) -> None:
        env = {**os.environ, **child.spec.env}
        child.process = subprocess.Popen(
            child.spec.argv, env=env, stdin=subprocess.DEVNULL,
            preexec_fn=_die_with_parent if sys.platform.startswith("linux") else None,
        )
        child.started = time.monotonic()
        child.restart_at = None
        log.info("started %s (pid %d)", child.spec.name, child.process.pid)

    def step(self) -> bool:
        """Reap exited children and restart those that are due; False once nothing is left to run."""
        now = time.monotonic()
        for child in self._children.values():
            if child.process is not None and (code := child.process.poll()) is not None:
                self._exited(child, code, now)
            if child.process is None and child.restart_at is not None and now >= child.restart_at:
                child.restarts += 1
                self._spawn(child)
        return any(not c.finished for c in self._children.values())

    def _exited(self, child: _Child, code: int, now: float) -> None:
        ran = now - child.started
        child.process = None
        child.exit_code = code
        how = f"signal {-code}" if code < 0 else f"code {code}"
        if code == 0 or not child.spec.restart:
            child.finished = True
            log.info("%s exited with %s after %.1f s", child.spec.name, how, ran)
            return
        if ran >= self.stable_s:
            child.failures = 0
        delay = min(self.backoff_s * 2**child.failures, self.max_backoff_s)
        child.failures += 1
        child.restart_at = now + delay
        log.warning("%s exited with %s after %.1f s; restarting in %.1f s (restart %d)",
                    child.spec.name, how, ran, delay, child.restarts + 1)

    def run(self, stop: threading.Event, poll_s: float = 0.05) -> None:
        """Supervise until ``stop`` is set or every child has finished, then stop them all."""
        try:
            while not stop.is_set() and self.step():
                stop.wait(poll_s)
        finally:
            self.stop()

    def stop(self) -> None:
        """SIGTERM every child, SIGKILL those still up after ``grace_s``, reap all."""
        running = [c.process for c in self._children.values() if c.process and c.process.poll() is None]
        for process in running:
            process.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + self.grace_s
        for process in running:
            try:
                process.wait(timeout=max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                log.warning("pid %d ignored SIGTERM for %.1f s, killing it", process.pid, self.grace_s)
                process.kill()
                process.wait()
        for child in self._children.values():
            child.process = None
            child.restart_at = None
            child.finished = True
