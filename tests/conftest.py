"""Shared fixtures: a private Zenoh router per test, and processes that are always stopped.

Integration tests never touch the default local router on 7447. Each test gets

* ``router``: an in-process Zenoh router listening on a free loopback port (multicast
  scouting off), closed after the test;
* ``bus``: that endpoint, a unique rig, the ``BusConfig`` for sessions opened in the test
  process and the environment for child processes (``ARTRACK_CONNECT``,
  ``ARTRACK_ROUTER_AUTOSTART=0``, ``ARTRACK_RIG``, and an ``ARTRACK_TEST_ID`` marker);
* ``session``: a Zenoh session on that bus, closed in ``finally``;
* ``procs``: starts child processes in their own process group with output to files, and
  at teardown SIGTERMs then SIGKILLs every group and fails the test when any process that
  carries the test's marker is still alive.

The project is imported inside the fixtures so unit tests pay nothing for it; Zenoh is imported
once by ``tiers`` (below), to guard against it.

Tiers (markers declared in pyproject.toml; ``make test-fast`` leaves both out, ``make test`` runs all):

* ``integration``: starts processes or opens a Zenoh session. Every test under tests/integration
  carries it; any other test that does either must too.
* ``slow``: runs a tracker, SLAM or a calibration over a whole sequence of frames. Every test under
  tests/accuracy carries it.

``tiers`` (autouse) holds this: a test under those folders without its marker fails, and a test
without ``integration`` fails as soon as it starts a process or opens a Zenoh session.
"""

from __future__ import annotations

import contextlib
import multiprocessing.process
import os
import signal
import socket
import subprocess
import sys
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path

import pytest

STOP_GRACE_S = 5.0
TESTS = Path(__file__).resolve().parent
FOLDER_MARKERS = {"integration": "integration", "accuracy": "slow"}
"""The marker every test under ``tests/<folder>`` carries."""
PROCESS_STARTS = ((subprocess.Popen, "__init__"), (multiprocessing.process.BaseProcess, "start"), (os, "fork"),
                  (os, "posix_spawn"), (os, "posix_spawnp"), (os, "system"))
"""Every way a test starts a process: subprocess, multiprocessing, and the os calls beneath them."""


def pytest_configure(config):
    """Let Ctrl-C reach the processes the tests start, which inherit an ignored SIGINT: a suite run in the
    background of a shell without job control (CI scripts, ``make test &``) has SIGINT ignored, and a
    Python program that starts so never turns Ctrl-C into KeyboardInterrupt.

    Then load matplotlib's font list: on a machine where it has never run, matplotlib lists the system's
    fonts by running ``fc-list`` the first time a figure module is imported, which ``tiers`` would take for
    a unit test (a marker sheet's PDF) starting a process."""
    if signal.getsignal(signal.SIGINT) == signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    import matplotlib.font_manager  # noqa: F401


@pytest.fixture(autouse=True)
def tiers(request, monkeypatch):
    """Hold the tiers (module docstring): fail a test under tests/integration or tests/accuracy without its
    folder's marker, and a test without ``integration`` that starts a process or opens a Zenoh session."""
    path = request.node.path
    folder = path.relative_to(TESTS).parts[0] if path.is_relative_to(TESTS) else ""
    marker = FOLDER_MARKERS.get(folder)
    if marker is not None and request.node.get_closest_marker(marker) is None:
        pytest.fail(f"every test under tests/{folder} is marked {marker}: "
                    f"`pytestmark = pytest.mark.{marker}` in {path.name}")
    if request.node.get_closest_marker("integration") is not None:
        return
    import zenoh

    def refuse(what: str):
        def refused(*args, **kwargs):
            pytest.fail(f"{request.node.nodeid} {what} but is not marked integration (`pytestmark = "
                        f"pytest.mark.integration`, or `@pytest.mark.integration` on the test)")
        return refused

    for owner, name in PROCESS_STARTS:
        monkeypatch.setattr(owner, name, refuse(f"starts a process ({owner.__name__}.{name})"))
    monkeypatch.setattr(zenoh, "open", refuse("opens a Zenoh session"))


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def marked_pids(marker: str) -> list[int]:
    """Pids of live (non-zombie) processes whose environment holds ``ARTRACK_TEST_ID=marker``."""
    needle = f"ARTRACK_TEST_ID={marker}".encode()
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit() or int(entry.name) == os.getpid():
            continue
        try:
            environ = (entry / "environ").read_bytes()
            status = (entry / "status").read_text()
        except OSError:
            continue
        zombie = any(line.startswith("State:") and "Z" in line.split()[1] for line in status.splitlines())
        if not zombie and needle in environ.split(b"\0"):
            found.append(int(entry.name))
    return found


@dataclass
class Bus:
    """One test's private bus."""

    endpoint: str
    rig: str
    marker: str
    config: object  # services.bus.session.BusConfig
    env: dict[str, str] = field(default_factory=dict)

    @property
    def keys(self):  # protocol.keys.Keys
        return self.config.keys


@pytest.fixture
def router():
    """An in-process Zenoh router on a free 127.0.0.1 port; yields its endpoint ``tcp/127.0.0.1:PORT``.

    It opens without Zenoh's scouting delay (500 ms by default): with multicast off and nothing to
    connect to it has no one to scout, and every integration test would wait that long to start."""
    import zenoh

    from services.launcher.router import router_config

    zenoh.init_log_from_env_or("error")
    session, last_error = None, None
    for _ in range(5):  # another process may grab the port between free_port() and open()
        endpoint = f"tcp/127.0.0.1:{free_port()}"
        try:
            config = router_config((endpoint,), (), None)
            config.insert_json5("scouting/delay", "0")
            session = zenoh.open(config)
            break
        except zenoh.ZError as exc:
            last_error = exc
    if session is None:
        pytest.fail(f"could not start a test router: {last_error}")
    try:
        yield endpoint
    finally:
        session.close()


@pytest.fixture
def unused_endpoint() -> str:
    """``tcp/127.0.0.1:PORT`` where nothing listens (for tests of unreachable buses)."""
    return f"tcp/127.0.0.1:{free_port()}"


@pytest.fixture
def bus(router) -> Bus:
    """Bus settings of this test: its router, a unique rig, and the child-process environment."""
    from services.bus.session import BusConfig

    marker = uuid.uuid4().hex[:12]
    rig = f"t{marker}"
    config = BusConfig(connect=(router,), rig=rig, autostart_router=False)
    env = {
        **os.environ,
        "ARTRACK_CONNECT": router,
        "ARTRACK_ROUTER_AUTOSTART": "0",
        "ARTRACK_RIG": rig,
        "ARTRACK_TEST_ID": marker,
        "PYTHONUNBUFFERED": "1",
    }
    for name in ("ARTRACK_MODE", "ARTRACK_LISTEN", "ARTRACK_NAMESPACE", "ZENOH_CONFIG", "ARTRACK_LOG_FORMAT"):
        env.pop(name, None)
    return Bus(endpoint=router, rig=rig, marker=marker, config=config, env=env)


@pytest.fixture
def session(bus):
    """A Zenoh peer session of the test process on the test's bus (closed after the test)."""
    from services.bus.session import open_session

    opened = open_session(bus.config)
    try:
        yield opened
    finally:
        opened.close()


class Proc:
    """A started child process; its stdout and stderr go to files."""

    def __init__(self, name: str, argv: list[str], popen: subprocess.Popen, out: Path, err: Path):
        self.name = name
        self.argv = argv
        self.popen = popen
        self.out_path = out
        self.err_path = err

    @property
    def pid(self) -> int:
        return self.popen.pid

    def poll(self) -> int | None:
        return self.popen.poll()

    def wait(self, timeout: float) -> int:
        """Exit code; raises subprocess.TimeoutExpired when still running after ``timeout``."""
        return self.popen.wait(timeout)

    @property
    def stdout(self) -> str:
        return self.out_path.read_text(errors="replace")

    @property
    def stderr(self) -> str:
        return self.err_path.read_text(errors="replace")

    def describe(self) -> str:
        return f"{self.name} (pid {self.pid}, rc {self.poll()})\n--- stdout:\n{self.stdout}\n--- stderr:\n{self.stderr}"


class Processes:
    """Starts processes for one test and stops every one of them afterwards."""

    def __init__(self, bus: Bus, folder: Path):
        self.bus = bus
        self.folder = folder
        self.started: list[Proc] = []

    def start(self, argv: list[str], *, name: str = "proc", env: dict[str, str | None] | None = None) -> Proc:
        """Start ``argv`` in a new process group with the bus environment, updated by ``env`` (None = unset)."""
        index = len(self.started)
        out, err = self.folder / f"{index:02d}-{name}.out", self.folder / f"{index:02d}-{name}.err"
        environ = {**self.bus.env, **(env or {})}
        environ = {k: v for k, v in environ.items() if v is not None}
        with open(out, "wb") as stdout, open(err, "wb") as stderr:
            popen = subprocess.Popen(argv, env=environ, stdin=subprocess.DEVNULL,
                                     stdout=stdout, stderr=stderr, start_new_session=True)
        proc = Proc(name, argv, popen, out, err)
        self.started.append(proc)
        return proc

    def artrack(self, *args: str, name: str | None = None, env: dict[str, str | None] | None = None) -> Proc:
        """Start ``artrack ARGS...`` (as ``python -m services.cli``, the launcher's own way)."""
        return self.start([sys.executable, "-m", "services.cli", *args], name=name or args[0], env=env)

    def run(self, *args: str, timeout: float = 30.0, env: dict[str, str | None] | None = None) -> Proc:
        """Run ``artrack ARGS...`` to completion (killed and failed after ``timeout``)."""
        proc = self.artrack(*args, env=env)
        try:
            proc.wait(timeout)
        except subprocess.TimeoutExpired:
            self._stop(proc, grace_s=0.0)
            pytest.fail(f"`artrack {' '.join(args)}` did not finish within {timeout} s\n{proc.describe()}")
        return proc

    @staticmethod
    def _signal_group(proc: Proc, signum: int) -> None:
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.killpg(proc.pid, signum)

    def _stop(self, proc: Proc, grace_s: float) -> None:
        self._signal_group(proc, signal.SIGTERM)
        with contextlib.suppress(subprocess.TimeoutExpired):
            proc.popen.wait(grace_s)
        self._signal_group(proc, signal.SIGKILL)  # the group may outlive its leader
        with contextlib.suppress(subprocess.TimeoutExpired):
            proc.popen.wait(STOP_GRACE_S)

    def stop_all(self) -> list[int]:
        """Stop every started process group; return pids of marked processes that were still left."""
        running = [p for p in self.started if p.poll() is None]
        for proc in running:
            self._signal_group(proc, signal.SIGTERM)
        deadline = time.monotonic() + STOP_GRACE_S
        for proc in running:
            with contextlib.suppress(subprocess.TimeoutExpired):
                proc.popen.wait(max(0.0, deadline - time.monotonic()))
        for proc in self.started:
            self._signal_group(proc, signal.SIGKILL)
        for proc in self.started:
            with contextlib.suppress(subprocess.TimeoutExpired):
                proc.popen.wait(STOP_GRACE_S)
        # Anything carrying the marker escaped its group (or was never in one): kill it and say so.
        deadline = time.monotonic() + 2.0
        left = marked_pids(self.bus.marker)
        while left and time.monotonic() < deadline:
            time.sleep(0.05)
            left = marked_pids(self.bus.marker)
        for pid in left:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
        return left


@pytest.fixture
def procs(bus, tmp_path):
    """Start processes on the test's bus; all of them are stopped when the test ends, pass or fail."""
    processes = Processes(bus, tmp_path)
    try:
        yield processes
    finally:
        left = processes.stop_all()
        if left:
            pytest.fail(f"processes left behind after the test (killed now): {left}")
