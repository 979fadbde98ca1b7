"""Zenoh session configs, the one place both client apps and artrack's own processes build them.

The client library may depend on nothing but ``protocol`` and zenoh, and a client must open its
session exactly as the nodes do (same endpoints, same scouting, same security), so the config
layer lives here and ``services.bus.session`` builds on it.
"""

from __future__ import annotations

import json

import zenoh

from services.bus.security import Security

LOCAL_ROUTER = "tcp/127.0.0.1:7447"
"""Where processes on one machine meet when nothing else is said."""

RECONNECT = {"period_init_ms": 250, "period_max_ms": 2000, "period_increase_factor": 2}
"""Zenoh's back-off between tries of a connect endpoint, while it waits for the first connection and
after a router it was connected to has gone: 0.25 s, doubling up to 2 s (Zenoh's own default is 1 s
up to 4 s)."""


def session_config(mode: str, *, listen: tuple[str, ...] = (), connect: tuple[str, ...] = (),
                   security: Security | None = None) -> zenoh.Config:
    """A Zenoh config in ``mode`` with explicit endpoints, multicast scouting off and ``security``
    (TLS, credentials) applied; ValueError when ``security`` does not fit the mode or endpoints.

    A session that loses an endpoint tries it again with the ``RECONNECT`` back-off, so a router that
    restarts is rejoined by itself.

    Shared memory is set up when the session opens rather than on the first large message: set up
    lazily, the first frames of a stream went over TCP, filled the two-batch queue and a second
    camera's first frame was dropped.
    """
    config = zenoh.Config()
    config.insert_json5("mode", json.dumps(mode))
    config.insert_json5("scouting/multicast/enabled", "false")
    config.insert_json5("listen/endpoints", json.dumps(list(listen)))
    config.insert_json5("connect/endpoints", json.dumps(list(connect)))
    config.insert_json5("connect/retry", json.dumps(RECONNECT))
    config.insert_json5("transport/shared_memory/mode", json.dumps("init"))
    if security is not None:
        security.check(mode, listen, connect)
        security.apply(config)
    return config


def patient(config: zenoh.Config, attempt_ms: int) -> zenoh.Config:
    """``config`` changed so that opening a session keeps trying the connect endpoints (with Zenoh's
    retry back-off) for ``attempt_ms`` before giving up, instead of failing at once in client mode."""
    config.insert_json5("connect/timeout_ms", json.dumps(attempt_ms))
    return config
