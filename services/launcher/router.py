"""A Zenoh router process: where hosts (and the local peers) meet.

``idle_exit_s`` makes the router leave once no session has been connected to it for that
long; the router that artrack starts on demand uses it, a router started by hand does not.

A hardened router listens on ``tls/`` endpoints with its certificate (``Security``), checks
``user:password`` lines of a users file (Zenoh's ``usrpwd`` dictionary), and applies an access
file (``services.launcher.access``).
"""

from __future__ import annotations

import json
import logging
import threading
import time
from pathlib import Path

import zenoh

from services.bus.security import Security
from services.bus.session import BusError, close_session
from services.bus.settings import read_zenoh_config
from services.bus.transport import session_config
from services.launcher.access import access_control, read_access

log = logging.getLogger(__name__)


def router_config(listen: tuple[str, ...], connect: tuple[str, ...], zenoh_config: Path | None, *,
                  security: Security | None = None, users: Path | None = None,
                  access: Path | None = None) -> zenoh.Config:
    """A router config: a Zenoh config file when given, else explicit endpoints, no multicast;
    then ``security`` (TLS files), the ``users`` file and the ``access`` file on top.
    BusError naming a config file that is missing or invalid, ValueError naming any other file
    or setting that cannot work."""
    if zenoh_config is not None:
        config = read_zenoh_config(zenoh_config)
        config.insert_json5("mode", '"router"')
        if security is not None:
            security.apply(config)
    else:
        config = session_config("router", listen=listen, connect=connect, security=security)
    if users is not None:
        if not users.is_file():
            raise ValueError(f"users file {users} does not exist")
        config.insert_json5("transport/auth/usrpwd/dictionary_file", json.dumps(str(users)))
    if access is not None:
        config.insert_json5("access_control", json.dumps(access_control(read_access(access))))
    return config


def run_router(config: zenoh.Config, stop: threading.Event, idle_exit_s: float | None = None) -> None:
    """Serve as a router until ``stop`` is set, or until idle for ``idle_exit_s``."""
    zenoh.init_log_from_env_or("error")
    try:
        session = zenoh.open(config)
    except zenoh.ZError as exc:
        raise BusError(f"cannot start the router ({config.get_json('listen/endpoints')}): {exc}") from exc
    log.info("router %s listening on %s", session.info.zid(), config.get_json("listen/endpoints"))
    idle_since = time.monotonic()
    try:
        while not stop.wait(0.5):
            if list(session.info.transports()):
                idle_since = time.monotonic()
            elif idle_exit_s is not None and time.monotonic() - idle_since > idle_exit_s:
                log.info("no session connected for %.0f s, leaving", idle_exit_s)
                break
    finally:
        close_session(session)
