"""A Zenoh router process: where hosts (and the local peers) meet.

``idle_exit_s`` makes the router leave once no session has been connected to it for that
long; the router that artrack starts on demand uses it, a router started by hand does not.
"""

from __future__ import annotations

import logging
import threading
import time
from pathlib import Path

import zenoh

from services.client.transport import session_config
from services.runtime.bus import BusError

log = logging.getLogger(__name__)


def router_config(listen: tuple[str, ...], connect: tuple[str, ...], zenoh_config: Path | None) -> zenoh.Config:
    """A router config: a Zenoh config file when given, else explicit endpoints, no multicast."""
    if zenoh_config is not None:
        config = zenoh.Config.from_file(str(zenoh_config))
        config.insert_json5("mode", '"router"')
        return config
    return session_config("router", listen=listen, connect=connect)


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
        session.close()
