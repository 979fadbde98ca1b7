"""Opening a Zenoh session the artrack way.

The settings (config file, endpoints, mode, namespace, rig) are the client library's
``BusSettings``, so apps and nodes open their sessions alike. An artrack process given none
of them runs as a peer listening on a free loopback port and connects to the local router at
``tcp/127.0.0.1:7447``, starting one in the background when none answers. That router exits by
itself a while after its last peer has gone. Peers that met through it also connect to each
other directly, so data does not pass through it.

Every session tries a lost endpoint again by itself (Zenoh's reconnect, see
``services.bus.transport.RECONNECT``), so a restarted router is rejoined without help. A
long-running process (``retry``: nodes and ``artrack up``) also waits for a router that is not
there yet: it logs one error naming the endpoint and keeps trying, where a one-shot command
fails at once with ``BusError``.
"""

from __future__ import annotations

import logging
import os
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import ClassVar

import zenoh
from pydantic import Field

from services.bus.settings import BusEnvironment, BusError, BusSettings
from services.bus.transport import LOCAL_ROUTER, patient

__all__ = ["LOCAL_ROUTER", "BusConfig", "BusError", "ensure_local_router", "open_session", "reachable"]

log = logging.getLogger(__name__)

LOCAL_ROUTER_IDLE_EXIT_S = 60.0
RETRY_ATTEMPT_MS = 1000
"""How long one attempt to open a retrying session waits before Python gets control back (signals)."""


class ProcessEnvironment(BusEnvironment):
    """The bus variables, plus those of starting the local router and waiting for the bus."""

    autostart_router: str | None = Field(None, alias="ARTRACK_ROUTER_AUTOSTART")
    router_wait_s: str | None = Field(None, alias="ARTRACK_ROUTER_WAIT_S")
    retry: str | None = Field(None, alias="ARTRACK_RETRY")


class BusConfig(BusSettings):
    """Bus settings of an artrack process: the shared ones, plus starting the local router on demand."""

    ENVIRONMENT: ClassVar[type[BusEnvironment]] = ProcessEnvironment

    autostart_router: bool = True
    router_wait_s: float = Field(default=5.0, ge=0)
    retry: bool = False
    """Wait for an unreachable router (client mode) instead of failing: for long-running processes."""


CALLBACK_THREAD = "(pyo3-closure)"
"""How the name of a thread on which Zenoh runs Python callbacks ends (``Thread-N (pyo3-closure)``)."""
CALLBACK_JOIN_S = 2.0


def close_session(session: zenoh.Session, timeout_s: float = CALLBACK_JOIN_S) -> None:
    """Close ``session``, then wait (up to ``timeout_s``) for the threads on which Zenoh ran its callbacks to end.

    Zenoh runs each subscriber's or queryable's Python callback on a thread of its own, a daemon when it was
    declared from a daemon thread (a node's thread in a process group). Closing the session ends them, but
    not at once: one still inside Zenoh, finishing a callback, when the interpreter finalises is torn down
    there, and the process aborts (SIGABRT, "FATAL: exception not rethrown") instead of exiting with its code.
    """
    session.close()
    deadline = time.monotonic() + timeout_s
    for thread in threading.enumerate():
        if thread is not threading.current_thread() and thread.name.endswith(CALLBACK_THREAD):
            thread.join(max(0.0, deadline - time.monotonic()))


def open_session(bus: BusConfig) -> zenoh.Session:
    """Open a Zenoh session for ``bus``; start the local router first when it is needed and absent."""
    zenoh.init_log_from_env_or("error")
    if bus.uses_local_router and bus.autostart_router:
        ensure_local_router(bus.router_wait_s)
    if not bus.retry:
        return bus.open()
    return _open_retrying(bus)


def _open_retrying(bus: BusConfig) -> zenoh.Session:
    """Open the session, trying again until the bus answers; the first failure is logged once.

    Only an absent bus is waited for: when every endpoint accepted a TCP connection before an
    attempt and the session still fails (credentials or TLS refused, a listen port in use),
    waiting cannot help, so the BusError comes at once. (Checked before the attempt, not after:
    a router that starts while an attempt runs is a bus that just came up, not one that refuses.)
    """
    config = patient(bus.zenoh(), RETRY_ATTEMPT_MS)
    failed_at = None
    while True:
        attempt_ends = time.monotonic() + RETRY_ATTEMPT_MS / 1000
        answered = bool(bus.endpoints) and all(reachable(endpoint) for endpoint in bus.endpoints)
        try:
            session = zenoh.open(config)
        except zenoh.ZError as exc:
            if answered:
                raise BusError(f"cannot open the Zenoh session ({bus.mode} via {bus.where}), which answers, so "
                               f"waiting will not help: {exc}") from exc
            if failed_at is None:
                failed_at = time.monotonic()
                log.error("cannot reach the bus (%s via %s): %s; retrying until it answers", bus.mode, bus.where,
                          exc)
            time.sleep(max(0.0, attempt_ends - time.monotonic()))  # a refusal that comes at once must not spin
            continue
        if failed_at is not None:
            log.info("joined the bus via %s after %.1f s", bus.where, time.monotonic() - failed_at)
        return session


def _endpoint_address(endpoint: str) -> tuple[str, int]:
    host, _, port = endpoint.split("/", 1)[1].rpartition(":")
    return host.strip("[]"), int(port)


def reachable(endpoint: str, timeout_s: float = 0.3) -> bool:
    """True when a TCP connection to ``endpoint`` (``tcp/HOST:PORT``) succeeds."""
    try:
        with socket.create_connection(_endpoint_address(endpoint), timeout=timeout_s):
            return True
    except OSError:
        return False


def runtime_dir() -> Path:
    """A per-user folder for the local router's log."""
    base = os.environ.get("XDG_RUNTIME_DIR") or "/tmp"
    folder = Path(base) / f"artrack-{os.getuid()}"
    folder.mkdir(parents=True, exist_ok=True)
    return folder


def ensure_local_router(wait_s: float) -> None:
    """Start ``artrack router`` on the local endpoint unless something already listens there."""
    if reachable(LOCAL_ROUTER):
        return
    log_path = runtime_dir() / "router.log"
    command = [sys.executable, "-m", "services.cli", "router", "--listen", LOCAL_ROUTER,
               "--idle-exit", str(LOCAL_ROUTER_IDLE_EXIT_S)]
    with open(log_path, "ab") as sink:
        process = subprocess.Popen(command, stdin=subprocess.DEVNULL, stdout=sink, stderr=sink,
                                   start_new_session=True, cwd="/")
    deadline = time.monotonic() + wait_s
    while time.monotonic() < deadline:
        if reachable(LOCAL_ROUTER):  # ours, or one another process started at the same moment
            log.info("started the local router on %s (pid %d, log %s)", LOCAL_ROUTER, process.pid, log_path)
            return
        time.sleep(0.05)
    log.warning("the local router on %s did not come up within %.1f s (see %s); running as a lone peer",
                LOCAL_ROUTER, wait_s, log_path)
