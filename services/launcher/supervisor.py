"""Process supervision: start commands, restart the ones that die, stop them all.

A child that exits with code 0 has finished its job and is left alone. One that exits with
code 2 (``EXIT_CANNOT_RUN``: it cannot do its job as asked, a node's ``NodeError``) would fail
alike however often it started, so it is marked failed at once, logged as an error and left
down. One that dies otherwise (another non-zero code or a signal) while the supervisor runs is
restarted after a back-off that doubles with each quick failure (0.5 s, 1 s, 2 s ... up to
10 s) and resets once the child has run for ``stable_s``. The restart budget bounds a crash
loop: a child that would need more than ``max_restarts`` restarts within ``window_s`` seconds
is marked failed, logged as an error and left down. The others keep running either way.
Stopping sends SIGTERM to every child, waits up to ``grace_s``, then SIGKILLs what is left and
reaps everything. On Linux each child also asks the kernel for SIGTERM should the supervisor
die without stopping it, so no child outlives it.

Each child's stderr passes through the supervisor line by line (to its own stderr), and the
last line a child wrote before it exited is kept as the reason it exited (``reason``, a log
line reduced to its message; the signal, when one killed it): a job can say why a node
ended in one line. Every child
is started with ``ARTRACK_RESTART`` set to the number of times it was restarted before
(``services.runtime.restarts``), and with the priority and CPUs its ``ProcessSpec`` asks for
(``services.launcher.scheduling``), set before its command runs. A child whose command cannot be
started at all (a missing program, a priority or CPUs the machine no longer allows) is marked
failed at once, with that reason, and the others go on.
"""

from __future__ import annotations

import contextlib
import ctypes
import functools
import json
import logging
import os
import re
import signal
import subprocess
import sys
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from services.launcher.scheduling import Scheduling, apply_scheduling
from services.runtime.logs import is_native_line
from services.runtime.restarts import EXIT_CANNOT_RUN, RESTART_ENV

log = logging.getLogger(__name__)

_PR_SET_PDEATHSIG = 1
RELAY_JOIN_S = 2.0
"""How long to wait, once a child exited, for the last of its stderr to come through."""

State = Literal["running", "backing_off", "failed", "finished"]


class SupervisorSettings(BaseModel):
    """Restart policy: back-off, restart budget and stop grace (a pipeline's ``[supervisor]`` table)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    backoff_s: float = Field(default=0.5, gt=0, le=3600, description="first restart delay, doubled per quick failure")
    max_backoff_s: float = Field(default=10.0, gt=0, le=3600, description="longest restart delay")
    stable_s: float = Field(default=10.0, gt=0, description="a child up this long has its back-off reset")
    max_restarts: int = Field(default=5, ge=0, description="restarts allowed within window_s; beyond: failed")
    window_s: float = Field(default=60.0, gt=0, description="the restart budget's sliding window")
    grace_s: float = Field(default=1.5, gt=0, le=60, description="SIGTERM to SIGKILL delay when stopping")

    @model_validator(mode="after")
    def _ordered(self) -> SupervisorSettings:
        if self.max_backoff_s < self.backoff_s:
            raise ValueError(f"max_backoff_s ({self.max_backoff_s}) is below backoff_s ({self.backoff_s})")
        return self


class RestartBudget:
    """At most ``max_restarts`` restarts within any ``window_s`` seconds (times from ``time.monotonic``)."""

    def __init__(self, max_restarts: int, window_s: float):
        self.max_restarts = max_restarts
        self.window_s = window_s
        self._times: deque[float] = deque()

    def allow(self, now: float) -> bool:
        """Whether one more restart at ``now`` fits; if it does, it is counted."""
        while self._times and now - self._times[0] >= self.window_s:
            self._times.popleft()
        if len(self._times) >= self.max_restarts:
            return False
        self._times.append(now)
        return True


@dataclass(frozen=True)
class ProcessSpec:
    """A command to keep running: ``argv`` with ``env`` added to the supervisor's environment, started with
    ``scheduling`` (its priority and CPUs)."""

    name: str
    argv: tuple[str, ...]
    env: dict[str, str] = field(default_factory=dict)
    restart: bool = True
    scheduling: Scheduling = Scheduling()


@dataclass(frozen=True)
class ChildHealth:
    """One child now: its state (see ``protocol.system.SupervisedNode``), pid, uptime, restarts, last exit code
    and the last stderr line it wrote before that exit ('' while it never exited)."""

    name: str
    state: State
    pid: int | None
    uptime_s: float
    restarts: int
    exit_code: int | None
    reason: str = ""


@dataclass
class _Child:
    spec: ProcessSpec
    budget: RestartBudget
    process: subprocess.Popen | None = None
    started: float = 0.0
    restarts: int = 0
    failures: int = 0
    restart_at: float | None = None
    finished: bool = False
    failed: bool = False
    exit_code: int | None = None
    last_line: str = ""
    reason: str = ""
    causes: deque[str] = field(default_factory=deque)
    relay: threading.Thread | None = None

    @property
    def state(self) -> State:
        if self.failed:
            return "failed"
        if self.finished:
            return "finished"
        return "backing_off" if self.process is None else "running"


_TEXT_LOG = re.compile(r"\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d+ [A-Z]+ (?:\[[^\]]*\] )?\S+: (?P<message>.*)")
"""A text log line (``services.runtime.logs``): time, level, [node], logger, then the message."""


def reason_of(line: str) -> str:
    """What a log line says: its message (a JSON line's with its exception's last line); any other line as is."""
    try:
        entry = json.loads(line)
    except ValueError:
        text = _TEXT_LOG.fullmatch(line)
        return text["message"] if text else line
    if not isinstance(entry, dict) or "message" not in entry:
        return line
    exception = str(entry.get("exception") or "").strip().splitlines()
    return f"{entry['message']}: {exception[-1]}" if exception else str(entry["message"])


def _reason(code: int, last_line: str) -> str:
    """Why a child exited with ``code``: the signal that killed it, else the last line it wrote."""
    if code < 0:
        try:
            return f"killed by {signal.Signals(-code).name}"
        except ValueError:
            return f"killed by signal {-code}"
    return reason_of(last_line) if last_line else f"exit code {code}, nothing on stderr"


def _relay(child: _Child, pipe) -> None:
    """Copy the child's stderr to ours line by line, keeping its last non-blank line of its own (Zenoh's
    log lines, in colour or as JSON records, are copied but never taken as the reason)."""
    with pipe:
        for raw in pipe:
            line = raw.decode(errors="replace")
            with contextlib.suppress(OSError, ValueError):  # our stderr gone: keep reading, so the child never blocks
                sys.stderr.write(line)
                sys.stderr.flush()
            if line.strip() and not is_native_line(line):
                child.last_line = line.strip()


def _die_with_parent() -> None:
    libc = ctypes.CDLL(None, use_errno=True)
    libc.prctl(_PR_SET_PDEATHSIG, signal.SIGTERM)


def _asked(scheduling: Scheduling) -> list[str]:
    """What ``scheduling`` asks for, in words (``nice -10``, ``CPUs [1]``); empty when nothing."""
    return ([] if scheduling.nice is None else [f"nice {scheduling.nice}"]) + \
        ([] if scheduling.cpus is None else [f"CPUs {list(scheduling.cpus)}"])


def _before_exec(scheduling: Scheduling) -> None:
    """In the child, before it runs its command: it dies with the supervisor, and runs as ``scheduling`` says."""
    _die_with_parent()
    apply_scheduling(scheduling)


class Supervisor:
    """Keeps a set of processes running (see the module docstring). Call from the main thread."""

    def __init__(self, specs: list[ProcessSpec], settings: SupervisorSettings | None = None):
        self.settings = settings or SupervisorSettings()
        self._children = {spec.name: _Child(spec, RestartBudget(self.settings.max_restarts, self.settings.window_s))
                          for spec in specs}
        self._lock = threading.Lock()

    def health(self) -> list[ChildHealth]:
        """Every child's state now (safe from other threads)."""
        now = time.monotonic()
        with self._lock:
            return [ChildHealth(name, c.state, c.process.pid if c.process else None,
                                now - c.started if c.process else 0.0, c.restarts, c.exit_code, c.reason)
                    for name, c in self._children.items()]

    def failure(self, name: str) -> str:
        """Why the child ``name`` was marked failed, in one line: that it cannot do its job and why (its
        reason, less the ``node NAME: `` a node's line starts with), or its exits within the budget and their
        cause."""
        child = self._children[name]
        if child.exit_code == EXIT_CANNOT_RUN:
            return (f"it cannot do its job (exit code {EXIT_CANNOT_RUN}, not restarted: it would fail alike): "
                    f"{child.reason.removeprefix(f'node {name}: ')}")
        causes = set(child.causes)
        said = f"each time: {child.reason}" if len(causes) == 1 else f"the last time: {child.reason}"
        return (f"it exited {len(child.causes)} times within {self.settings.window_s:.0f} s, more than its restart "
                f"budget ({self.settings.max_restarts} restarts) allows; {said}")

    def exit_codes(self) -> dict[str, int | None]:
        """The code each child last exited with (None while it never has)."""
        return {name: c.exit_code for name, c in self._children.items()}

    def update(self, spec: ProcessSpec) -> None:
        """Start the child named ``spec.name`` with ``spec`` from its next restart on."""
        with self._lock:
            self._children[spec.name].spec = spec

    def start(self) -> None:
        for child in self._children.values():
            self._spawn(child)

    def _spawn(self, child: _Child) -> None:
        env = {**os.environ, **child.spec.env, RESTART_ENV: str(child.restarts)}
        try:
            child.process = subprocess.Popen(
                child.spec.argv, env=env, stdin=subprocess.DEVNULL, stderr=subprocess.PIPE,
                preexec_fn=functools.partial(_before_exec, child.spec.scheduling) if sys.platform.startswith("linux")
                else None,
            )
        except (OSError, subprocess.SubprocessError) as exc:
            self._not_started(child, exc)
            return
        child.last_line = ""
        child.relay = threading.Thread(target=_relay, args=(child, child.process.stderr),
                                       name=f"stderr of {child.spec.name}", daemon=True)
        child.relay.start()
        child.started = time.monotonic()
        child.restart_at = None
        log.info("started %s (pid %d%s)", child.spec.name, child.process.pid,
                 "".join(f", {what}" for what in _asked(child.spec.scheduling)))

    def _not_started(self, child: _Child, error: Exception) -> None:
        """Mark ``child`` failed: its command could not be started (``error``), and would not be next time."""
        child.process, child.failed, child.exit_code = None, True, EXIT_CANNOT_RUN
        asked = _asked(child.spec.scheduling)
        if isinstance(error, subprocess.SubprocessError) and asked:
            child.reason = f"its process could not be given {' and '.join(asked)}: this machine does not allow it now"
        else:
            child.reason = f"it could not be started: {error}"
        log.error("%s: FAILED, left down: %s", child.spec.name, child.reason,
                  extra={"child": child.spec.name, "exit_code": EXIT_CANNOT_RUN, "restarts": child.restarts})

    def step(self) -> bool:
        """Reap exited children and restart those that are due; False once nothing is left to run."""
        now = time.monotonic()
        with self._lock:
            for child in self._children.values():
                if child.process is not None and (code := child.process.poll()) is not None:
                    self._exited(child, code, now)
                if child.process is None and child.restart_at is not None and now >= child.restart_at:
                    child.restarts += 1
                    self._spawn(child)
            return any(not (c.finished or c.failed) for c in self._children.values())

    def _exited(self, child: _Child, code: int, now: float) -> None:
        ran = now - child.started
        child.process = None
        child.exit_code = code
        if child.relay is not None:
            child.relay.join(RELAY_JOIN_S)
        child.reason = _reason(code, child.last_line)
        while child.causes and len(child.causes) > self.settings.max_restarts:
            child.causes.popleft()
        if code != 0:
            child.causes.append(child.reason)
        how = f"signal {-code}" if code < 0 else f"code {code}"
        if code == 0 or not child.spec.restart:
            child.finished = True
            log.info("%s exited with %s after %.1f s", child.spec.name, how, ran)
            return
        if code == EXIT_CANNOT_RUN or not child.budget.allow(now):
            child.failed = True
            log.error("%s exited with %s after %.1f s; FAILED, left down: %s", child.spec.name, how, ran,
                      self.failure(child.spec.name),
                      extra={"child": child.spec.name, "exit_code": code, "restarts": child.restarts})
            return
        if ran >= self.settings.stable_s:
            child.failures = 0
        delay = min(self.settings.backoff_s * 2**child.failures, self.settings.max_backoff_s)
        child.failures += 1
        child.restart_at = now + delay
        log.warning("%s exited with %s after %.1f s (%s); restarting in %.1f s (restart %d)",
                    child.spec.name, how, ran, child.reason, delay, child.restarts + 1,
                    extra={"child": child.spec.name, "exit_code": code, "restarts": child.restarts})

    def run(self, stop: threading.Event, poll_s: float = 0.05) -> None:
        """Supervise until ``stop`` is set or every child has finished or failed, then stop them all."""
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
        grace_s = self.settings.grace_s
        deadline = time.monotonic() + grace_s
        for process in running:
            try:
                process.wait(timeout=max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                log.warning("pid %d ignored SIGTERM for %.1f s, killing it", process.pid, grace_s)
                process.kill()
                process.wait()
        with self._lock:
            for child in self._children.values():
                if child.relay is not None:
                    child.relay.join(RELAY_JOIN_S)
                child.process = None
                child.restart_at = None
                child.finished = True
