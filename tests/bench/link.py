"""The bench process's end of the link: the spawned sink process and a Zenoh session connected to it,
and a private ``artrack router`` with the child processes that use it.

By default the sink listens on a free loopback port (found by binding ``127.0.0.1:0``); the
bench process's session connects to it, peer to peer, multicast scouting off, no router. A
sink given an ``AppLink`` is a client app instead (``services.client``): it connects to the
bench process's own listening peer session (``direct_app``), or both are client-mode sessions
of a router (``routed_app``), so every message passes through that router. Closing a ``Sink``
(it is a context manager) closes the session and stops the process, killing it if it does not
quit within ``QUIT_S``, whatever happened before.
"""

from __future__ import annotations

import json
import os
import queue
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import zenoh

from protocol.keys import Keys
from services.bus.session import BusConfig, reachable
from services.bus.transport import session_config
from tests.bench.sink import REPLY

T = TypeVar("T")

ROOT = Path(__file__).resolve().parents[2]
REPLY_S = 30.0
QUIT_S = 5.0
ROUTER_START_S = 20.0
RIG = "bench"


class BenchError(RuntimeError):
    """The sink died, did not answer in time, or reported a fault."""


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


@dataclass(frozen=True)
class AppLink:
    """A sink that is a client app connects in ``mode`` to ``endpoint``; ``config`` is the bench
    process's session, opened before the sink starts; ``keys`` are the rig's (pose keys only)."""

    mode: str
    endpoint: str
    config: zenoh.Config
    keys: Keys


def direct_app(keys: Keys) -> AppLink:
    """The app connects as a peer straight to the bench process, which listens on a free port."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    return AppLink("peer", endpoint, session_config("peer", listen=(endpoint,)), keys)


def routed_app(router: str, keys: Keys) -> AppLink:
    """The app and the bench process are both clients of the router at ``router``."""
    return AppLink("client", router, session_config("client", connect=(router,)), keys)


def at_rate(items: Iterable[T], period_s: float) -> Iterator[T]:
    """``items`` one every ``period_s`` seconds (0: as fast as they are taken), sleeping until each is due."""
    due = time.perf_counter()
    for item in items:
        due += period_s
        while (wait := due - time.perf_counter()) > 0:
            time.sleep(wait)
        yield item


def stop_processes(processes: list[subprocess.Popen]) -> None:
    """Terminate every process still running, then wait up to 5 s for each (killed after that)."""
    for process in processes:
        if process.poll() is None:
            process.terminate()
    for process in processes:
        try:
            process.wait(5)
        except subprocess.TimeoutExpired:
            process.kill()


def cpu_seconds(pid: int) -> float:
    """User + system CPU time a live process has used so far, from /proc."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


class Sink:
    """A running sink process and the bench process's session connected to it (see the module docstring)."""

    def __init__(self, app: AppLink | None = None) -> None:
        if app is None:
            endpoint = f"tcp/127.0.0.1:{free_port()}"
            args, config = [endpoint], session_config("peer", connect=(endpoint,))
        else:
            args, config = ["--app", app.mode, app.endpoint, app.keys.namespace, app.keys.rig], app.config
        self.session: zenoh.Session | None = None
        self._process: subprocess.Popen | None = None
        self._replies: queue.Queue[dict[str, Any] | None] = queue.Queue()
        try:
            if app is not None:  # the app connects to this session, or needs its router up, so it opens first
                self.session = zenoh.open(config)
            self._process = subprocess.Popen([sys.executable, "-m", "tests.bench.sink", *args], cwd=ROOT,
                                             stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
            threading.Thread(target=self._pump, daemon=True).start()
            self._reply()
            if self.session is None:  # a plain sink listens: connect once it answered
                self.session = zenoh.open(config)
        except BaseException:
            self.close()
            raise

    def __enter__(self) -> Sink:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def start(self, key: str, reader: dict[str, Any]) -> None:
        """Have the sink subscribe to ``key`` and read each sample as ``reader`` says."""
        self._command({"cmd": "start", "key": key, "reader": reader})

    def stop(self, sent: int) -> dict[str, Any]:
        """Tell the sink ``sent`` messages went out; its report once they arrived (see ``sink``)."""
        report = self._command({"cmd": "stop", "sent": sent})
        if report["refused"]:
            raise BenchError(f"the sink could not read {report['refused']} of {sent} messages")
        return report

    def close(self) -> None:
        if self.session is not None:
            self.session.close()
            self.session = None
        if self._process is not None and self._process.poll() is None:
            try:
                self._send({"cmd": "quit"})
                self._process.wait(QUIT_S)
            except (OSError, subprocess.TimeoutExpired):
                self._process.kill()
                self._process.wait()

    def _command(self, command: dict[str, Any]) -> dict[str, Any]:
        try:
            self._send(command)
        except OSError as exc:
            raise BenchError(f"the sink is gone (code {self._process.poll()})") from exc
        answer = self._reply()
        if "error" in answer:
            raise BenchError(answer["error"])
        return answer

    def _send(self, command: dict[str, Any]) -> None:
        assert self._process.stdin is not None
        self._process.stdin.write(json.dumps(command) + "\n")
        self._process.stdin.flush()

    def _reply(self) -> dict[str, Any]:
        try:
            answer = self._replies.get(timeout=REPLY_S)
        except queue.Empty:
            raise BenchError(f"the sink did not answer within {REPLY_S:.0f} s") from None
        if answer is None:
            raise BenchError(f"the sink exited (code {self._process.wait()})")
        return answer

    def _pump(self) -> None:
        """Queue the sink's replies; pass anything else it prints on to stderr."""
        assert self._process.stdout is not None
        for line in self._process.stdout:
            if line.startswith(REPLY):
                self._replies.put(json.loads(line[len(REPLY):]))
            else:
                sys.stderr.write(line)
        self._replies.put(None)


class Bench:
    """A private ``artrack router`` process on a free port and the child processes of a benchmark, their
    stderr logged into ``folder``, their environment (``env``) on that router; everything is stopped on exit."""

    def __init__(self, folder: Path):
        self.folder = folder
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        self.env = {**os.environ, "ARTRACK_CONNECT": self.endpoint, "ARTRACK_ROUTER_AUTOSTART": "0",
                    "ARTRACK_RIG": RIG, "ARTRACK_LOG_LEVEL": "WARNING"}
        self.bus = BusConfig(connect=(self.endpoint,), rig=RIG, autostart_router=False)
        self.children: list[subprocess.Popen] = []
        self.start("router", "--listen", self.endpoint)
        deadline = time.monotonic() + ROUTER_START_S
        while not reachable(self.endpoint):
            if time.monotonic() > deadline:
                self.__exit__()
                raise BenchError(f"the router on {self.endpoint} did not come up within {ROUTER_START_S:.0f} s")
            time.sleep(0.05)

    def start(self, *args: str, module: str = "services.cli") -> subprocess.Popen:
        log = open(self.folder / f"{len(self.children):02d}-{args[0]}.log", "wb")  # noqa: SIM115
        child = subprocess.Popen([sys.executable, "-m", module, *args], cwd=ROOT, env=self.env,
                                 stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=log)
        log.close()
        self.children.append(child)
        return child

    def __enter__(self) -> Bench:
        return self

    def __exit__(self, *exc: object) -> None:
        for child in self.children:
            if child.poll() is None:
                child.terminate()
        for child in self.children:
            try:
                child.wait(5)
            except subprocess.TimeoutExpired:
                child.kill()
                child.wait()
