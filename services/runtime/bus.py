"""Opening a Zenoh session the artrack way.

Three ways to say where the bus is, in order of precedence:

1. a Zenoh JSON5/YAML config file (``--zenoh-config FILE`` or ``ZENOH_CONFIG``), used as is;
2. explicit endpoints: ``--connect tcp/HOST:PORT`` (a router or a peer) and ``--listen``,
   in ``peer`` or ``client`` mode (``ARTRACK_CONNECT``, ``ARTRACK_LISTEN``, ``ARTRACK_MODE``);
3. nothing: the process runs as a peer listening on a free loopback port and connects to
   the local router at ``tcp/127.0.0.1:7447``, starting one in the background when none
   answers. That router exits by itself a while after its last peer has gone. Peers that met
   through it also connect to each other directly, so data does not pass through it.

Multicast scouting is always off unless a config file turns it on: nothing leaks onto
the network by accident.
"""

from __future__ import annotations

import logging
import os
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Literal

import zenoh
from pydantic import BaseModel, ConfigDict, Field, field_validator

from protocol.keys import Keys, check_name
from services.client.transport import LOCAL_ROUTER, session_config

log = logging.getLogger(__name__)

LOCAL_ROUTER_IDLE_EXIT_S = 60.0


class BusConfig(BaseModel):
    """Where a process finds the bus, and which namespace and rig it works in."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    mode: Literal["peer", "client"] = "peer"
    connect: tuple[str, ...] = ()
    listen: tuple[str, ...] = ()
    zenoh_config: Path | None = None
    namespace: str = "ar"
    rig: str = "rig0"
    autostart_router: bool = True
    router_wait_s: float = Field(default=5.0, ge=0)

    @field_validator("namespace")
    @classmethod
    def _namespace(cls, value: str) -> str:
        return check_name(value, "namespace", segments=True)

    @field_validator("rig")
    @classmethod
    def _rig(cls, value: str) -> str:
        return check_name(value, "rig")

    @field_validator("connect", "listen")
    @classmethod
    def _endpoints(cls, value: tuple[str, ...]) -> tuple[str, ...]:
        for endpoint in value:
            if "/" not in endpoint:
                raise ValueError(f"endpoint {endpoint!r} must look like tcp/HOST:PORT")
        return value

    @property
    def keys(self) -> Keys:
        return Keys(self.namespace, self.rig)

    @property
    def uses_local_router(self) -> bool:
        return self.zenoh_config is None and not self.connect

    @classmethod
    def from_env(cls, environ: dict[str, str] | None = None, **overrides: object) -> BusConfig:
        """Settings from ``ARTRACK_*`` / ``ZENOH_CONFIG`` variables, then ``overrides`` (None = unset)."""
        env = os.environ if environ is None else environ
        values: dict[str, object] = {}
        split = lambda text: tuple(p.strip() for p in text.split(",") if p.strip())  # noqa: E731
        if env.get("ARTRACK_MODE"):
            values["mode"] = env["ARTRACK_MODE"]
        if env.get("ARTRACK_CONNECT"):
            values["connect"] = split(env["ARTRACK_CONNECT"])
        if env.get("ARTRACK_LISTEN"):
            values["listen"] = split(env["ARTRACK_LISTEN"])
        if env.get("ZENOH_CONFIG"):
            values["zenoh_config"] = env["ZENOH_CONFIG"]
        if env.get("ARTRACK_NAMESPACE"):
            values["namespace"] = env["ARTRACK_NAMESPACE"]
        if env.get("ARTRACK_RIG"):
            values["rig"] = env["ARTRACK_RIG"]
        if env.get("ARTRACK_ROUTER_AUTOSTART"):
            values["autostart_router"] = env["ARTRACK_ROUTER_AUTOSTART"] not in ("0", "false", "no")
        if env.get("ARTRACK_ROUTER_WAIT_S"):
            values["router_wait_s"] = env["ARTRACK_ROUTER_WAIT_S"]
        values.update({k: v for k, v in overrides.items() if v is not None and v != ()})
        return cls.model_validate(values)

    def to_env(self) -> dict[str, str]:
        """The variables that make ``from_env`` rebuild this config in a child process."""
        env = {
            "ARTRACK_MODE": self.mode,
            "ARTRACK_CONNECT": ",".join(self.connect),
            "ARTRACK_LISTEN": ",".join(self.listen),
            "ARTRACK_NAMESPACE": self.namespace,
            "ARTRACK_RIG": self.rig,
            "ARTRACK_ROUTER_AUTOSTART": "1" if self.autostart_router else "0",
            "ARTRACK_ROUTER_WAIT_S": repr(self.router_wait_s),
            "ZENOH_CONFIG": str(self.zenoh_config) if self.zenoh_config else "",
        }
        return env

    def zenoh(self) -> zenoh.Config:
        """The Zenoh config these settings describe."""
        if self.zenoh_config is not None:
            if not self.zenoh_config.is_file():
                raise BusError(f"Zenoh config file {self.zenoh_config} does not exist")
            try:
                return zenoh.Config.from_file(str(self.zenoh_config))
            except zenoh.ZError as exc:
                raise BusError(f"Zenoh config file {self.zenoh_config} is invalid: {exc}") from exc
        connect = self.connect or (LOCAL_ROUTER,)
        listen = self.listen or (("tcp/127.0.0.1:0",) if self.mode == "peer" else ())
        return session_config(self.mode, listen=listen, connect=connect)


class BusError(RuntimeError):
    """The bus could not be opened as configured; the message says what and why."""


def open_session(bus: BusConfig) -> zenoh.Session:
    """Open a Zenoh session for ``bus``; start the local router first when it is needed and absent."""
    zenoh.init_log_from_env_or("error")
    if bus.uses_local_router and bus.autostart_router:
        ensure_local_router(bus.router_wait_s)
    config = bus.zenoh()
    try:
        return zenoh.open(config)
    except zenoh.ZError as exc:
        where = bus.zenoh_config or ", ".join(bus.connect or (LOCAL_ROUTER,))
        raise BusError(f"cannot open the Zenoh session ({bus.mode} via {where}): {exc}") from exc


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
