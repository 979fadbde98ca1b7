"""``artrack up`` as a daemon: restart budget, ``artrack status`` (--json, --check), JSON logs,
client subscriptions nobody feeds, SIGHUP reload and ``artrack config``."""

from __future__ import annotations

import json
import os
import signal
import sys
import time

import numpy as np
import pytest

from protocol.detections import MarkerDetections
from protocol.poses import Pose
from protocol.tracking_state import TrackingState
from services.bus.pubsub import Inbox, Role
from services.client.client import connect

from .support import START_S, collect, json_lines, pid_alive, wait_until

pytestmark = pytest.mark.integration


def _bus_table(bus) -> str:
    return f'[bus]\nrig = "{bus.rig}"\nconnect = ["{bus.endpoint}"]\nautostart_router = false\n'


def _status(procs, *args: str):
    """``artrack status ARGS`` run to completion."""
    return procs.run("status", "--timeout", "1", *args, timeout=30)


def _nodes(procs) -> dict:
    """``{node: status JSON}`` of the one pipeline ``artrack status --json`` reports ({} if none)."""
    report = json.loads(_status(procs, "--json").stdout)
    return {n["name"]: n for p in report["pipelines"] for n in p["nodes"]}


def test_budget_status_check_clients_and_json_logs(bus, procs, tmp_path):
    path = tmp_path / "daemon.toml"
    path.write_text(_bus_table(bus) + """
[supervisor]
backoff_s = 0.1
max_restarts = 1
window_s = 60

[nodes.cam]
kind = "capture"
cameras = ["cam0"]
fps = 20
scene = { width = 64, height = 64 }

[nodes.echo]
kind = "echo"
camera = "cam0"
""")
    # --log-format json on the launcher: its nodes inherit it through ARTRACK_LOG_FORMAT.
    launcher = procs.start([sys.executable, "-m", "services.cli", "--log-format", "json", "up", str(path)], name="up")

    def healthy() -> dict | None:
        assert launcher.poll() is None, launcher.describe()
        nodes = _nodes(procs)
        ok = {"cam", "echo"} <= nodes.keys() and all(n["state"] == "running" and n["stats"] for n in nodes.values())
        return nodes if ok and nodes["echo"]["stats"]["processing_ms_p50"] is not None else None

    nodes = wait_until(healthy, START_S, "both nodes running with stats")
    assert nodes["cam"]["stats"]["out_hz"] > 0 and nodes["echo"]["stats"]["in_hz"] > 0
    echo = nodes["echo"]["stats"]
    assert echo["processing_ms_p99"] >= echo["processing_ms_p50"]
    # Each frame's age when echoed covers its trip here and its processing, so every percentile does too.
    assert echo["latency_ms_p99"] >= echo["latency_ms_p50"] >= echo["processing_ms_p50"] > 0
    assert _status(procs, "--check").poll() == 0 and _status(procs, "--check", "--here").poll() == 0

    # A client app asking for a target nobody tracks: an empty stream, and status says so.
    with connect(connect=bus.endpoint, rig=bus.rig, app="tracker") as client:
        stream = client.poses("cam9/**", idle_timeout_s=0.5)
        assert list(stream) == []
        text = _status(procs).stdout
        assert f"app tracker waits for {bus.keys.pose_pattern('cam9/**')} but no node publishes it" in text, text
        assert "echo" in text and "running" in text

    # kill -9 echo: restarted once (the budget); killed again: failed, left down, cam untouched.
    first = nodes["echo"]["pid"]
    os.kill(first, signal.SIGKILL)
    again = wait_until(lambda: (n := _nodes(procs)).get("echo", {}).get("pid") not in (None, first)
                       and n["echo"]["state"] == "running" and n, START_S, "echo restarted")
    assert again["echo"]["restarts"] == 1
    os.kill(again["echo"]["pid"], signal.SIGKILL)
    failed = wait_until(lambda: (n := _nodes(procs))["echo"]["state"] == "failed" and n, START_S, "echo failed")
    assert failed["echo"]["pid"] is None and failed["echo"]["exit_code"] == -9 and failed["echo"]["restarts"] == 1
    assert failed["cam"]["state"] == "running" and failed["cam"]["pid"] == nodes["cam"]["pid"]
    assert pid_alive(nodes["cam"]["pid"])
    check = _status(procs, "--check")
    assert check.poll() == 1 and "unhealthy: node echo is failed" in check.stdout

    # Logs: every line of the launcher and of its nodes is one JSON object.
    logs = json_lines(launcher.stderr)
    assert {"time", "level", "logger", "node", "message"} <= logs[0].keys()
    fail = [e for e in logs if e["level"] == "error" and "FAILED" in e["message"]]
    assert fail and fail[0]["child"] == "echo" and fail[0]["exit_code"] == -9
    assert any(e["node"] == "cam" and e["logger"] == "artrack.capture" for e in logs)

    launcher.popen.send_signal(signal.SIGTERM)
    assert launcher.wait(10) == 1, launcher.describe()  # a node ended failed


def test_no_pipeline_fails_the_check(bus, procs):
    check = _status(procs, "--check")
    assert check.poll() == 1 and "unhealthy: no `artrack up` or `artrack run` answered" in check.stdout


def _marker_pipeline(bus, fps: float, scene_width: int = 320) -> str:
    return _bus_table(bus) + f"""
[nodes.cam]
kind = "capture"
source = "synthetic:markers"
loop = true
fps = {fps}
scene = {{ width = {scene_width}, height = 240 }}

[nodes.markers]
kind = "markers"
camera = "cam0"
"""


def test_sighup_and_config_change_live_parameters(bus, procs, session, tmp_path):
    path = tmp_path / "markers.toml"
    path.write_text(_marker_pipeline(bus, fps=4))
    launcher = procs.artrack("up", str(path), name="up")
    detections = Inbox(session, bus.keys.markers("cam0"), MarkerDetections, Role.RESULT, depth=100)
    try:
        nodes = wait_until(lambda: (n := _nodes(procs)).keys() >= {"cam", "markers"}
                           and all(x["stats"] for x in n.values()) and n, START_S, "the pipeline to be up")
        collect(detections, lambda got: any(len(m.ids) for m in got))

        # SIGHUP with a reloadable change (capture fps 4 -> 40): applied live, frames come faster.
        path.write_text(_marker_pipeline(bus, fps=40))
        launcher.popen.send_signal(signal.SIGHUP)
        wait_until(lambda: "reload: node cam applied" in launcher.stderr, START_S, "the reload to apply")
        wait_until(lambda: (_nodes(procs)["cam"]["stats"] or {}).get("out_hz", 0) > 20, START_S,
                   "the capture rate to follow fps 40")

        # SIGHUP with a non-reloadable change (the scene): refused, naming node and field; nothing restarts.
        path.write_text(_marker_pipeline(bus, fps=40, scene_width=200))
        launcher.popen.send_signal(signal.SIGHUP)
        wait_until(lambda: "running pipeline is unchanged" in launcher.stderr, START_S, "the reload to be refused")
        assert "node cam: field scene is not reloadable" in launcher.stderr
        shown = procs.run("config", "cam", timeout=30)
        assert shown.poll() == 0 and json.loads(shown.stdout)["params"] == {"fps": 40.0}

        # artrack config: a detector threshold no marker passes -> detections go empty.
        done = procs.run("config", "markers", "--set", 'parameters={"minMarkerPerimeterRate": 3.9}', timeout=30)
        answer = json.loads(done.stdout)
        assert done.poll() == 0 and answer["refused"] == {} and "parameters" in answer["applied"], done.describe()
        collect(detections, 0)  # what came before the change
        collect(detections, lambda got: len(got) >= 5 and all(len(m.ids) == 0 for m in got[-5:]))
        refused = procs.run("config", "markers", "--set", "dictionary=DICT_5X5_100", timeout=30)
        assert refused.poll() == 1
        assert json.loads(refused.stdout)["refused"] == {"dictionary": "not reloadable: needs a restart"}
        after = _nodes(procs)
        assert {n: after[n]["pid"] for n in after} == {n: nodes[n]["pid"] for n in nodes}
        assert all(n["restarts"] == 0 for n in after.values())
    finally:
        detections.close()


def _tracking_after(poses, seq: int, child: str | None = None) -> Pose:
    """The first tracking pose (of ``child``, if given) of a frame after ``seq``."""
    def fits(p: Pose) -> bool:
        return p.state is TrackingState.TRACKING and p.header.seq > seq and child in (None, p.child_frame_id)

    return next(p for p in collect(poses, lambda got: any(fits(p) for p in got)) if fits(p))


def test_the_marker_pose_node_takes_new_corner_noise_and_detector_thresholds_live(bus, procs, session, tmp_path):
    path = tmp_path / "marker.toml"
    path.write_text(_bus_table(bus) + """
[nodes.cam]
kind = "capture"
source = "synthetic:markers"
fps = 15
loop = true
scene = { fps = 3000.0 }

[nodes.marker]
kind = "marker_pose"
camera = "cam0"
marker_length = 0.05
""")
    procs.artrack("up", str(path), name="up")
    poses = Inbox(session, bus.keys.poses(), Pose, Role.RESULT, depth=10_000)
    try:
        before = _tracking_after(poses, -1)

        # Corner noise 0.5 -> 2 px: covariances 16 times larger. The scene's clock runs 200 times slower than
        # the frames go out, so the view barely moves however long the change takes to arrive on a busy machine.
        done = procs.run("config", "marker", "--set", "corner_sigma_px=2.0", timeout=30)
        assert done.poll() == 0 and json.loads(done.stdout)["refused"] == {}, done.describe()
        assert json.loads(done.stdout)["params"]["corner_sigma_px"] == 2.0  # a value, not JSON text
        assert json.loads(done.stdout)["applied"] == {"corner_sigma_px": 2.0}  # as the node holds it, not as typed
        applied_by = max(p.header.seq for p in [before, *collect(poses, 0)]) + 1  # frames after it saw the change
        after = _tracking_after(poses, applied_by, before.child_frame_id)
        scale = np.diag(np.reshape(after.covariance, (6, 6))) / np.diag(np.reshape(before.covariance, (6, 6)))
        assert np.all((scale > 4) & (scale < 64)), scale

        # A detector threshold no marker passes: every tracked marker is reported lost, then nothing tracks.
        done = procs.run("config", "marker", "--set", 'parameters={"minMarkerPerimeterRate": 3.9}', timeout=30)
        assert done.poll() == 0 and "parameters" in json.loads(done.stdout)["applied"], done.describe()
        since = collect(poses, 0)
        since += collect(poses, lambda got: any(p.state is TrackingState.LOST for p in since + got))
        applied_by = max(p.header.seq for p in since) + 1
        time.sleep(1.0)
        assert [p for p in collect(poses, 0) if p.header.seq > applied_by and p.state is TrackingState.TRACKING] == []
    finally:
        poses.close()


def test_a_process_group_is_supervised_as_one_process_with_its_nodes_each_on_the_bus(bus, procs, tmp_path):
    path = tmp_path / "group.toml"
    path.write_text(_bus_table(bus) + """
[supervisor]
backoff_s = 0.1

[nodes.cam]
kind = "capture"
cameras = ["cam0"]
fps = 20
scene = { width = 64, height = 64 }
process = "camera"

[nodes.echo]
kind = "echo"
camera = "cam0"
process = "camera"
""")
    launcher = procs.start([sys.executable, "-m", "services.cli", "--log-format", "json", "up", str(path)], name="up")

    def running(previous: int | None = None) -> dict | None:
        assert launcher.poll() is None, launcher.describe()
        nodes = _nodes(procs)
        up = {"cam", "echo"} <= nodes.keys() and all(n["state"] == "running" and n["stats"] for n in nodes.values())
        fresh = up and nodes["cam"]["pid"] != previous and nodes["echo"]["stats"]["pid"] == nodes["echo"]["pid"]
        return nodes if fresh and nodes["echo"]["stats"]["in_hz"] > 0 else None

    nodes = wait_until(running, START_S, "both nodes of the group running, frames echoed")
    assert nodes["cam"]["pid"] == nodes["echo"]["pid"] == nodes["echo"]["stats"]["pid"]
    os.kill(nodes["cam"]["pid"], signal.SIGKILL)  # the group dies as one process, and comes back as one
    again = wait_until(lambda: running(nodes["cam"]["pid"]), START_S, "the group restarted")
    assert again["cam"]["restarts"] == again["echo"]["restarts"] == 1
    launcher.popen.send_signal(signal.SIGTERM)
    assert launcher.wait(10) == 0, launcher.describe()
    logs = json_lines(launcher.stderr)
    assert any(e["node"] == "echo" and e["logger"] == "artrack.echo" for e in logs)
    assert any(e["node"] == "cam" and e["logger"] == "artrack.capture" for e in logs)
