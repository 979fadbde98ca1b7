"""Pipelines sharing one bus: the demo on a rig of its own, one process per node name and rig,
``list`` showing every process, and where a pipeline's rig comes from."""

from __future__ import annotations

import os
import re
import signal
import socket
import time

import pytest

from protocol.codec import encode
from protocol.message import Header
from protocol.system import NodeStats

from .support import START_S, kill_hard, start_node, states, wait_live, wait_until

pytestmark = pytest.mark.integration

DEMO_S = 180
ECHO = {"camera": "cam0"}


def _summary(text: str) -> dict[str, str]:
    return dict(re.findall(r"^\s*([a-z /0-9]+):\s+(.*)$", text, re.MULTILINE))


def _default_rig_capture(procs):
    """``artrack run capture --source synthetic:markers --loop`` on the default rig (no ARTRACK_RIG), publishing."""
    capture = procs.artrack("run", "capture", "--source", "synthetic:markers", "--loop", name="capture",
                            env={"ARTRACK_RIG": None})
    wait_until(lambda: "job on ar/rig0" in capture.stderr or capture.poll() is not None, START_S,
               "the looping capture job to start")
    assert capture.poll() is None, capture.describe()
    return capture


def test_demo_runs_on_its_own_rig_beside_a_pipeline_on_the_default_rig(bus, procs, tmp_path):
    capture = _default_rig_capture(procs)
    demo = procs.run("demo", "--runs", str(tmp_path), env={"ARTRACK_RIG": None}, timeout=DEMO_S)
    assert demo.poll() == 0, demo.describe()
    assert re.search(rf"on ar/demo-{demo.pid};", demo.stdout), demo.stdout
    summary = _summary(demo.stdout)
    assert summary["frames"].startswith("150 of 150 replayed, 150 with ground truth, 150 with poses"), demo.stdout
    assert capture.poll() is None, "the other pipeline should be left running"


def test_demo_honours_rig_and_namespace_flags(bus, procs, tmp_path):
    _default_rig_capture(procs)
    demo = procs.run("demo", "--runs", str(tmp_path), "--rig", "nc2", "--namespace", "ns2", timeout=DEMO_S)
    assert demo.poll() == 0, demo.describe()
    assert "on ns2/nc2;" in demo.stdout, demo.stdout
    recorded = _summary(demo.stdout)["recorded"]
    info = procs.run("info", recorded)
    assert re.search(r"^recording\s+ns2/nc2, keys", info.stdout, re.MULTILINE), info.stdout


def test_interrupted_demo_reports_what_it_did_and_exits_130(bus, procs, tmp_path):
    demo = procs.artrack("demo", "--runs", str(tmp_path))
    wait_until(lambda: "frame   30" in demo.stdout or demo.poll() is not None, DEMO_S, "the demo's second line")
    os.killpg(demo.pid, signal.SIGINT)  # as Ctrl-C does: the whole foreground group
    assert demo.wait(60) == 130, demo.describe()
    played = int(re.match(r"(\d+) of 150 replayed", _summary(demo.stdout)["frames"]).group(1))
    assert 30 <= played < 150, demo.stdout
    assert f"interrupted after {played} of 150 frames" in demo.stderr, demo.stderr


def _refusals(text: str) -> list[str]:
    return [line for line in text.splitlines() if "already running" in line]


def test_a_second_node_under_a_live_name_is_refused_naming_the_holder(bus, procs, session):
    first = start_node(procs, "echo", "relay", **ECHO)
    wait_live(session, bus.keys, {"relay"}, [first])
    wait_until(lambda: "relay" in states(session, bus.keys), START_S, "the node to answer its state query")
    second = procs.run("node", "echo", "--name", "relay", "--params", '{"camera": "cam0"}')
    assert second.poll() == 2, second.describe()
    refusals = _refusals(second.stderr)
    assert len(refusals) == 1 and "Traceback" not in second.stderr, second.stderr
    assert f"node relay is already running on ar/{bus.rig} (pid {first.pid} on {socket.gethostname()}" \
        in refusals[0], refusals
    assert first.poll() is None and states(session, bus.keys)["relay"].pid == first.pid


def test_a_second_job_of_the_same_tracker_on_one_rig_is_refused_naming_the_holder(bus, procs):
    marker = ("run", "marker", "--source", "synthetic:markers", "--loop", "--marker-length", "0.05")
    first = procs.artrack(*marker, name="first")
    wait_until(lambda: "job on" in first.stderr or first.poll() is not None, START_S, "the first job to start")
    assert first.poll() is None, first.describe()
    second = procs.run(*marker, timeout=60)
    assert second.poll() == 2, second.describe()
    assert f"node marker-cam0 is already running on ar/{bus.rig}" in second.stderr, second.stderr
    assert "node capture (capture) up" not in second.stderr, "the second job started its source beside the first one's"
    assert first.poll() is None, first.describe()


def test_a_node_restarted_at_once_after_kill_9_is_not_refused_by_its_former_token(bus, procs, session):
    first = start_node(procs, "echo", "relay", **ECHO)
    wait_live(session, bus.keys, {"relay"}, [first])
    wait_until(lambda: "relay" in states(session, bus.keys), START_S, "the node to answer its state query")
    kill_hard(first)
    again = start_node(procs, "echo", "relay", **ECHO)
    wait_until(lambda: (s := states(session, bus.keys).get("relay")) and s.pid == again.pid, START_S,
               "the restarted node to answer with its pid")
    assert again.poll() is None and not _refusals(again.stderr), again.describe()


def _answer_as(session, keys, name: str, pid: int, uptime_s: float):
    """A state queryable answering for node ``name`` as a process ``pid`` up for ``uptime_s`` elsewhere."""

    def answer(query) -> None:
        stats = NodeStats(header=Header(stamp_ns=time.time_ns()), node=name, kind="echo", host="elsewhere",
                          pid=pid, uptime_s=uptime_s)
        query.reply(keys.state(name), encode(stats))

    return session.declare_queryable(keys.state(name), answer)


def test_a_node_that_missed_an_elder_of_its_name_stops_itself_with_one_line(bus, procs, session):
    # An elder whose token this node does not see (as when both start at once on a loaded machine)
    # but which answers on the node's state key, as every node does.
    elder = _answer_as(session, bus.keys, "relay", 4242, 3600.0)
    try:
        node = start_node(procs, "echo", "relay", **ECHO)
        assert node.wait(START_S) == 2, node.describe()
        refusals = _refusals(node.stderr)
        assert len(refusals) == 1 and "(pid 4242 on elsewhere, kind echo" in refusals[0], node.stderr
        assert "stopping this later one" in refusals[0]
    finally:
        elder.undeclare()


def test_list_shows_every_process_of_a_name_and_nodes_that_hold_only_a_token(bus, procs, session):
    keys = bus.keys
    relay = start_node(procs, "echo", "relay", **ECHO)
    wait_live(session, keys, {"relay"}, [relay])

    twin = _answer_as(session, keys, "relay", 4242, 0.0)  # a second, younger process under the same name
    ghost = session.liveliness().declare_token(keys.node("ghost"))
    try:
        wait_live(session, keys, {"relay", "ghost"})
        listed = procs.run("list", "--timeout", "1.5")
        assert listed.poll() == 0, listed.describe()
        rows = [line.split() for line in listed.stdout.splitlines()[1:]]
        assert sorted((name, pid) for rig, name, kind, pid, *_ in rows if rig == bus.rig) == sorted(
            [("ghost", "-"), ("relay", "4242"), ("relay", str(relay.pid))]), listed.stdout
        refused = procs.run("node", "echo", "--name", "ghost", "--params", '{"camera": "cam0"}')
        assert refused.poll() == 2, refused.describe()
        assert "node ghost is already running" in refused.stderr and "its state did not answer" in refused.stderr
    finally:
        ghost.undeclare()
        twin.undeclare()


def test_environment_beats_a_pipeline_file_rig_with_one_notice(bus, procs, session, tmp_path):
    path = tmp_path / "relay.toml"
    path.write_text(f'[bus]\nrig = "filerig{bus.marker}"\n\n[nodes.relay]\nkind = "echo"\ncamera = "cam0"\n')
    up = procs.artrack("up", str(path))
    wait_live(session, bus.keys, {"relay"}, [up])
    notices = [line for line in up.stderr.splitlines() if "overrides" in line]
    assert notices == [line for line in notices if f"[bus] rig by ARTRACK_RIG={bus.rig}" in line] and \
        len(notices) == 1, up.stderr
