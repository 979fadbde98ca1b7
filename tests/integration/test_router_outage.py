"""Long-running processes ride out a router that is not there yet, or that dies and comes back.

The router here is ``artrack router`` in a process of its own (so it can be killed with
SIGKILL), and every session is in client mode, so the router is the only way between them.
"""

from __future__ import annotations

import json
import re
import time

import pytest

from protocol.sensors import Image
from services.bus.pubsub import Inbox, Role
from services.bus.session import open_session, reachable

from .support import ROOT, START_S, collect, kill_hard, start_node, start_router, wait_live, wait_until

pytestmark = pytest.mark.integration

SETTLE_S = 0.5
"""Time for messages already on their way when the router died to land (they are then drained)."""
DOWN_S = 3.0
"""How long the router stays dead: longer than the longest reconnect back-off (2 s), so the figure
printed is the worst case of a router restart as the apps see it."""


def client_env(endpoint: str) -> dict[str, str]:
    return {"ARTRACK_MODE": "client", "ARTRACK_CONNECT": endpoint}


DAEMONS = {
    "node": (["node", "echo", "--name", "early"], {"early"}),
    "up": (["up", str(ROOT / "pipelines" / "echo.toml")], {"cam", "echo"}),
}


@pytest.mark.parametrize("command", sorted(DAEMONS))
def test_a_client_daemon_waits_for_its_router_with_one_error_per_node_and_joins(bus, procs, unused_endpoint,
                                                                               command):
    argv, names = DAEMONS[command]
    waiting = len(names) + (command == "up")  # `up` itself waits too, to answer its health query
    daemon = procs.artrack(*argv, "--rig", bus.rig, env=client_env(unused_endpoint), name=command)
    wait_until(lambda: daemon.stderr.count("cannot reach the bus") == waiting, START_S,
               "every node to say the router is missing")
    time.sleep(2 * SETTLE_S)  # a few more attempts, which must stay quiet
    assert daemon.poll() is None, daemon.describe()

    start_router(procs, unused_endpoint)
    config = bus.config.model_copy(update={"connect": (unused_endpoint,), "mode": "client"})
    session = open_session(config)
    try:
        wait_live(session, config.keys, names, [daemon])
    finally:
        session.close()
    errors = [line for line in daemon.stderr.splitlines() if "ERROR" in line]
    assert len(errors) == waiting, daemon.stderr
    assert sorted(m[1] for line in errors if (m := re.search(r"ERROR \[([^\]]+)\]", line))) == sorted(names)
    for line in errors:
        assert unused_endpoint in line and "client" in line and "retrying" in line, line
    assert "Traceback" not in daemon.stderr
    assert daemon.stderr.count(f"joined the bus via {unused_endpoint}") == waiting, daemon.stderr


def test_nodes_and_a_subscriber_carry_on_after_the_router_is_killed_and_restarted(bus, procs, unused_endpoint):
    endpoint = unused_endpoint
    router = start_router(procs, endpoint)
    env = client_env(endpoint)
    capture = start_node(procs, "capture", "cam", env, source=["synthetic:markers"], fps=30, loop=True)
    echo = start_node(procs, "echo", "echo", env, camera="cam0")
    config = bus.config.model_copy(update={"connect": (endpoint,), "mode": "client"})
    session = open_session(config)
    try:
        wait_live(session, config.keys, {"cam", "echo"}, (capture, echo))
        echoed = Inbox(session, config.keys.echo("cam0"), Image, Role.RESULT)
        before = collect(echoed, 3)

        kill_hard(router)
        time.sleep(DOWN_S)
        last_seq = max(image.header.seq for image in [*before, *collect(echoed, 0)])
        procs.artrack("router", "--listen", endpoint, name="router-again")
        wait_until(lambda: reachable(endpoint), START_S, "the router to listen again", interval_s=0.01)
        restarted = time.monotonic()
        after = collect(echoed, lambda got: any(image.header.seq > last_seq for image in got))
        rejoined_s = time.monotonic() - restarted
        print(json.dumps({"figure": "router listening again to first echoed frame", "s": round(rejoined_s, 2)}))

        assert any(image.header.seq > last_seq for image in after)
        assert capture.poll() is None and echo.poll() is None, capture.describe() + echo.describe()
        wait_live(session, config.keys, {"cam", "echo"}, (capture, echo))
    finally:
        session.close()
