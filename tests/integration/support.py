"""Small helpers shared by the integration tests (fixtures live in ``tests/conftest.py``)."""

from __future__ import annotations

import json
import os
import signal
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

T = TypeVar("T")

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]
PROBE = HERE / "busprobe.py"
START_S = 20.0
"""Deadline for a process to come up and be seen on the bus (generous: CI shares its cores)."""
STOP_S = 5.0


def wait_until(probe: Callable[[], T], timeout_s: float, what: str, interval_s: float = 0.05) -> T:
    """Poll ``probe`` until it returns something truthy and return that; fail naming ``what``."""
    deadline = time.monotonic() + timeout_s
    while True:
        value = probe()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s:.0f} s waiting for {what} (last: {value!r})")
        time.sleep(interval_s)


def collect(inbox, enough: int | Callable[[list], bool], timeout_s: float = START_S) -> list:
    """Messages taken from ``inbox`` until there are ``enough`` (a count, or a test of the list so far)."""
    got: list = []
    done = (lambda messages: len(messages) >= enough) if isinstance(enough, int) else enough

    def probe() -> bool:
        while (received := inbox.take()) is not None:
            got.append(received.message)
        return done(got)

    wait_until(probe, timeout_s, f"{enough if isinstance(enough, int) else 'enough'} messages on {inbox.key}")
    return got


def published(proc) -> int | None:
    """How many messages the bus probe ``proc`` says it published; None until it has said so."""
    for line in proc.stdout.splitlines():
        if '"published"' in line:
            return json.loads(line)["published"]
    assert proc.poll() is None, f"the probe exited before publishing:\n{proc.describe()}"
    return None


def pid_alive(pid: int) -> bool:
    """True while ``pid`` names a process that has not exited (a zombie counts as exited)."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return False
    state = next((line.split()[1] for line in status.splitlines() if line.startswith("State:")), "")
    return state != "Z"


def probe_argv(*args: str) -> list[str]:
    """Command line of the bus probe helper (``busprobe.py``)."""
    return [sys.executable, str(PROBE), *args]


def json_lines(text: str) -> list[dict]:
    return [json.loads(line) for line in text.splitlines() if line.strip()]


def live_names(session, keys) -> set[str]:
    """Names of the nodes of ``keys.rig`` holding a liveliness token now."""
    from services.bus.discovery import live_nodes

    return {name for rig, name in live_nodes(session, keys, 0.3) if rig == keys.rig}


def states(session, keys) -> dict:
    """``{node name: NodeStats}`` answered on the state queryables of ``keys.rig``."""
    from services.bus.discovery import node_states

    return {name: s for (rig, name), s in node_states(session, keys, 2.0).items() if rig == keys.rig}


def start_node(procs, kind: str, name: str, env: dict[str, str] | None = None, flow: dict | None = None, **params):
    """``artrack node KIND --name NAME --params JSON`` on the test's bus (``env``: changes to its environment;
    ``flow``: its part in a lossless flow, a ``FlowPlan`` as a dict, as the launcher would give it)."""
    return procs.artrack("node", kind, "--name", name, "--params", json.dumps(params),
                         *(() if flow is None else ("--flow", json.dumps(flow))), name=name, env=env)


def wait_live(session, keys, names: set[str], procs_to_check=()) -> None:
    """Wait until every node in ``names`` holds its token (failing early when a process died)."""

    def ready() -> bool:
        for proc in procs_to_check:
            assert proc.poll() is None, f"a process exited early:\n{proc.describe()}"
        return names <= live_names(session, keys)

    wait_until(ready, START_S, f"nodes {sorted(names)} to be live")


def start_router(procs, endpoint: str, *, prefix: tuple[str, ...] = (), name: str = "router"):
    """``artrack router --listen ENDPOINT`` as a process of its own (``prefix``: e.g. ``ip netns exec NS``),
    returned once it says it listens."""
    proc = procs.start([*prefix, sys.executable, "-m", "services.cli", "router", "--listen", endpoint], name=name)

    def up() -> bool:
        assert proc.poll() is None, f"the router exited:\n{proc.describe()}"
        return "listening on" in proc.stderr

    wait_until(up, START_S, f"the router on {endpoint}")
    return proc


def kill_hard(proc) -> None:
    """SIGKILL ``proc`` (no chance to say goodbye to its peers) and reap it."""
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait(STOP_S)
