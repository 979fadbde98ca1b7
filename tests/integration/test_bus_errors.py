"""A process that cannot reach the bus says so in one line, naming the endpoint, and exits non-zero.

Zenoh's client mode fails at once when no router answers; peer mode keeps retrying in the
background by design (a peer may be the first one up), so the failure is tested in client mode.
A node waits for its router by default (see test_router_outage.py); ``ARTRACK_RETRY=0`` makes
it fail like the one-shot commands.
"""

from __future__ import annotations

import socket
import threading
from pathlib import Path

import pytest

from .support import START_S, wait_live, wait_until

pytestmark = pytest.mark.integration

COMMANDS = {
    "node": ["node", "echo", "--name", "e1"],
    "list": ["list", "--timeout", "0.5"],
    "echo": ["echo", "cam0/image", "--count", "1", "--timeout", "5"],
    "demo": ["demo", "--recording", str(Path(__file__).resolve().parents[2] / "recordings" / "pattern.mcap")],
}


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_client_with_no_router_fails_with_one_clear_line(procs, unused_endpoint, command):
    dead = unused_endpoint
    env = {"ARTRACK_RETRY": "0"} if command == "node" else None
    # It gives up rather than retrying: 15 s catches a retry loop (the time is the `refusals` benchmark's).
    done = procs.run(*COMMANDS[command], "--mode", "client", "--connect", dead, timeout=15, env=env)
    assert done.poll() not in (None, 0), done.describe()
    lines = [line for line in done.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, f"expected one error line:\n{done.stderr}"
    assert "ERROR" in lines[0] and dead in lines[0] and "client" in lines[0], lines[0]
    assert "Traceback" not in done.stderr
    assert done.stdout == ""


@pytest.mark.parametrize("command", ["list", "router"])
@pytest.mark.parametrize(("content", "reason"), [(None, "does not exist"), ("{bogus_key: 1}", "is invalid")])
def test_a_missing_or_invalid_zenoh_config_file_is_named(procs, tmp_path, command, content, reason):
    config = tmp_path / "zenoh.json5"
    if content is not None:
        config.write_text(content)
    done = procs.run(command, "--zenoh-config", str(config), timeout=30)
    assert done.poll() == 2, done.describe()
    lines = [line for line in done.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and str(config) in lines[0] and reason in lines[0], done.stderr
    assert "Traceback" not in done.stderr


@pytest.mark.parametrize(("variable", "value", "field"), [("ARTRACK_RETRY", "maybe", "retry"),
                                                        ("ARTRACK_RIG", "a/b", "rig")])
def test_a_bad_environment_variable_is_one_line_naming_it(procs, variable, value, field):
    done = procs.run("list", "--timeout", "0.5", env={variable: value}, timeout=30)
    assert done.poll() == 2, done.describe()
    lines = [line for line in done.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and f"{field} (env {variable})" in lines[0] and repr(value) in lines[0], done.stderr


def test_peer_started_before_its_router_joins_once_the_router_is_up(bus, procs, unused_endpoint):
    """Peer mode does not fail when the router is missing: it runs alone and connects when one appears."""
    import zenoh

    from services.bus.session import open_session
    from services.launcher.router import router_config

    node = procs.artrack("node", "echo", "--name", "early", env={"ARTRACK_CONNECT": unused_endpoint})
    wait_until(lambda: "node early (echo) up" in node.stderr, START_S, "the node to run without a router")
    assert node.poll() is None, node.describe()
    config = bus.config.model_copy(update={"connect": (unused_endpoint,)})
    router = zenoh.open(router_config((unused_endpoint,), (), None))
    try:
        session = open_session(config)
        try:
            wait_live(session, config.keys, {"early"}, [node])
        finally:
            session.close()
    finally:
        router.close()


def test_retrying_gives_up_at_once_when_the_endpoint_answers_but_the_session_fails(bus):
    """A daemon waits for a router that is down, not for one that answers and refuses: here a busy
    listen port beside a live router, then an endpoint that accepts TCP but never speaks Zenoh."""
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        busy = f"tcp/127.0.0.1:{taken.getsockname()[1]}"
        cases = {
            "busy listen port": bus.config.model_copy(update={"listen": (busy,), "retry": True}),
            "not a Zenoh router": bus.config.model_copy(update={"mode": "client", "connect": (busy,), "retry": True}),
        }
        for case, config in cases.items():
            outcome = opening(config, 10.0)
            assert isinstance(outcome, Exception) and "waiting will not help" in str(outcome), (case, outcome)
            assert config.where in str(outcome), case


def opening(config, timeout_s: float) -> Exception | str:
    """What opening a session with ``config`` ends in within ``timeout_s``: the error raised,
    ``"opened"``, or ``"still trying"`` (the attempt runs on in a daemon thread)."""
    from services.bus.session import open_session

    outcome: list[Exception | str] = []

    def attempt() -> None:
        try:
            open_session(config).close()
            outcome.append("opened")
        except Exception as exc:  # noqa: BLE001 - the test reports whatever it was
            outcome.append(exc)

    trying = threading.Thread(target=attempt, daemon=True)
    trying.start()
    trying.join(timeout_s)
    return outcome[0] if outcome else "still trying"
