"""Three hosts, played by network namespaces: router on A, pipeline on B, a client app on C.

A holds a bridge at 10.77.0.1/24; B (10.77.0.2) and C (10.77.0.3) each reach it over a veth
pair, and have nothing else but their own loopback: no route out, no proxy. B runs ``artrack
run marker`` and C runs ``examples/track_marker.py``, both in client mode against
``tcp/10.77.0.1:7447``, so the poses C prints went B -> A -> C over the veth links. The test
checks that, kills the router with SIGKILL (poses stop, and C cannot reach A's port any more:
nothing else carries them), restarts it, and checks the poses come back by themselves.

Building namespaces takes root; without it the test is skipped, naming the command refused.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass, field

import pytest

from .support import ROOT, START_S, kill_hard, start_router, wait_until

pytestmark = pytest.mark.integration

EXAMPLE = ROOT / "examples" / "track_marker.py"
ADDRESSES = {"a": "10.77.0.1", "b": "10.77.0.2", "c": "10.77.0.3"}
PORT = 7447
"""The router's usual port: each namespace has its own, so no other test can hold it."""
ROUTER = f"tcp/{ADDRESSES['a']}:{PORT}"
QUIET_S = 1.0
"""How long poses must stay away while the router is dead."""


class IpFailed(RuntimeError):
    """An ``ip`` command failed; the message is the command and what it said."""


def ip(*args: str) -> str:
    command = ["ip", *args]
    try:
        done = subprocess.run(command, capture_output=True, text=True, timeout=10)
    except FileNotFoundError as exc:
        raise IpFailed(f"`{' '.join(command)}`: {exc}") from exc
    if done.returncode != 0:
        raise IpFailed(f"`{' '.join(command)}` failed: {done.stderr.strip()}")
    return done.stdout


@dataclass
class Hosts:
    """The namespaces standing for hosts ``a``, ``b`` and ``c``."""

    names: dict[str, str] = field(default_factory=dict)

    def run(self, host: str) -> tuple[str, ...]:
        """The prefix that runs a command on ``host``."""
        return ("ip", "netns", "exec", self.names[host])

    def build(self, tag: str) -> None:
        """A bridge in ``a`` with the router's address; ``b`` and ``c`` each on a veth pair to it."""
        for host in ADDRESSES:
            name = f"art{tag}{host}"
            ip("netns", "add", name)
            self.names[host] = name
            ip("-n", name, "link", "set", "lo", "up")
        a = self.names["a"]
        ip("-n", a, "link", "add", "br0", "type", "bridge")
        ip("-n", a, "addr", "add", f"{ADDRESSES['a']}/24", "dev", "br0")
        ip("-n", a, "link", "set", "br0", "up")
        for host in ("b", "c"):
            ns, port = self.names[host], f"to{host}"
            ip("link", "add", port, "netns", a, "type", "veth", "peer", "name", "eth0", "netns", ns)
            ip("-n", a, "link", "set", port, "master", "br0", "up")
            ip("-n", ns, "addr", "add", f"{ADDRESSES[host]}/24", "dev", "eth0")
            ip("-n", ns, "link", "set", "eth0", "up")

    def remove(self) -> None:
        for name in self.names.values():
            subprocess.run(["ip", "netns", "delete", name], capture_output=True, timeout=10)

    def reaches(self, host: str, endpoint: str) -> bool:
        """Whether a TCP connection from ``host`` to ``endpoint`` succeeds."""
        probe = f"import sys; from services.bus.session import reachable; sys.exit(0 if reachable({endpoint!r}) else 1)"
        return subprocess.run([*self.run(host), sys.executable, "-c", probe], cwd=ROOT, timeout=30).returncode == 0

    def peers_of(self, host: str, port: int) -> set[str]:
        """Addresses with an established TCP connection to ``port`` on ``host``."""
        lines = ip("netns", "exec", self.names[host], "ss", "-Htn", "state", "established",
                   f"( sport = :{port} )").splitlines()
        return {line.split()[-1].rsplit(":", 1)[0] for line in lines if line.strip()}


@pytest.fixture
def hosts(bus) -> Iterator[Hosts]:
    """Three namespaces joined as in the module docstring, deleted after the test, pass or fail."""
    built = Hosts()
    try:
        try:
            built.build(bus.marker[:6])
        except IpFailed as exc:
            if not built.names:
                pytest.skip(f"cannot build network namespaces here: {exc}")
            raise
        yield built
    finally:
        built.remove()


def poses(app) -> list[str]:
    return [line for line in app.stdout.splitlines() if line.startswith("cam0/marker/")]


def test_poses_cross_three_hosts_and_come_back_after_a_router_restart(hosts, procs, bus):
    client = {"ARTRACK_MODE": "client", "ARTRACK_CONNECT": ROUTER}
    router = start_router(procs, ROUTER, prefix=hosts.run("a"))
    pipeline = procs.start([*hosts.run("b"), sys.executable, "-m", "services.cli", "run", "marker",
                            "--source", "synthetic:markers", "--loop", "--marker-length", "0.05"],
                           name="pipeline", env=client)
    app = procs.start([*hosts.run("c"), sys.executable, str(EXAMPLE), "cam0/**"], name="app", env=client)

    def flowing(router, at_least: int) -> bool:
        for proc in (router, pipeline, app):
            assert proc.poll() is None, proc.describe()
        return len(poses(app)) >= at_least

    wait_until(lambda: flowing(router, 5), START_S, "poses at the app on host C")
    assert {ADDRESSES["b"], ADDRESSES["c"]} <= hosts.peers_of("a", PORT)

    kill_hard(router)
    time.sleep(QUIET_S / 2)  # poses already on their way land
    stopped = len(poses(app))
    time.sleep(QUIET_S)
    assert len(poses(app)) == stopped, "poses reached C with the router dead: another path exists"
    assert not hosts.reaches("c", ROUTER)

    again = start_router(procs, ROUTER, prefix=hosts.run("a"), name="router-again")
    restarted = time.monotonic()
    wait_until(lambda: flowing(again, stopped + 1), START_S, "poses at the app after the router restart")
    print(json.dumps({"figure": "router listening again to the first pose at host C",
                      "s": round(time.monotonic() - restarted, 2)}))
    wait_until(lambda: flowing(again, stopped + 5), START_S, "poses to keep coming")
    assert {ADDRESSES["b"], ADDRESSES["c"]} <= hosts.peers_of("a", PORT)
