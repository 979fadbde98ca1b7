"""``artrack up``: a pipeline runs as processes, dead nodes come back, SIGTERM ends it all."""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import numpy as np
import pytest

from protocol.sensors import Image
from services.bus.pubsub import Inbox, Role
from services.calibration.camera_info import write_camera_info
from services.geometry.camera import CameraModel

from .support import ROOT, START_S, live_names, pid_alive, states, wait_live, wait_until

pytestmark = pytest.mark.integration


def _pipeline(bus, *, autostart: bool = False) -> str:
    return f"""
[bus]
rig = "{bus.rig}"
connect = ["{bus.endpoint}"]
autostart_router = {str(autostart).lower()}

[nodes.cam]
kind = "capture"
cameras = ["cam0"]
fps = 20
scene = {{ width = 64, height = 64 }}

[nodes.echo]
kind = "echo"
camera = "cam0"
"""


def _parent(pid: int) -> int:
    stat = Path(f"/proc/{pid}/stat").read_text()
    return int(stat.rsplit(")", 1)[1].split()[1])


def _fresh_frame(inbox: Inbox, after_ns: int) -> bool:
    """True once a message that arrived after ``after_ns`` (time.time_ns) was taken from ``inbox``."""
    received = inbox.recv(0.2)
    return received is not None and received.received_ns > after_ns


def test_up_runs_restarts_and_stops_a_pipeline(bus, procs, session, tmp_path):
    keys = bus.keys
    path = tmp_path / "pipeline.toml"
    path.write_text(_pipeline(bus))
    echoed = Inbox(session, keys.echo("cam0"), Image, Role.FRAME)
    # The bus comes from the file's [bus] table alone: the launcher's environment does not name it.
    launcher = procs.artrack("up", str(path), env={"ARTRACK_CONNECT": None, "ARTRACK_RIG": None})

    wait_live(session, keys, {"cam", "echo"}, [launcher])
    first = wait_until(lambda: (s := states(session, keys)).keys() >= {"cam", "echo"} and s,
                       START_S, "both nodes to answer their state query")
    pids = {name: first[name].pid for name in ("cam", "echo")}
    assert all(_parent(pid) == launcher.pid for pid in pids.values()), "nodes are not the launcher's children"
    assert (first["cam"].kind, first["echo"].kind) == ("capture", "echo")
    wait_until(lambda: _fresh_frame(echoed, 0), START_S, "frames on the echo key")

    # kill -9 the echo node: the launcher restarts it and frames flow through it again.
    os.kill(pids["echo"], signal.SIGKILL)
    wait_until(lambda: not pid_alive(pids["echo"]), 5, "the killed node to be gone")
    again = wait_until(lambda: (s := states(session, keys)).get("echo") and s["echo"].pid != pids["echo"] and s,
                       START_S, "the echo node to come back with a new pid")
    new_echo = again["echo"].pid
    restarted_ns = time.time_ns()  # the old echo is dead: frames arriving from now on are relayed by the new one
    assert _parent(new_echo) == launcher.pid
    assert again["cam"].pid == pids["cam"], "the capture node should not have been touched"
    assert "echo" in live_names(session, keys)
    wait_until(lambda: _fresh_frame(echoed, restarted_ns), START_S, "frames on the echo key after the restart")
    wait_until(lambda: (s := states(session, keys).get("echo")) and s.pid == new_echo and s.published > 0,
               START_S, "the restarted echo node to count what it relayed")
    assert "echo exited with signal 9" in launcher.stderr

    # SIGTERM the launcher: it stops (10 s catches a hang; the time is the `stops` benchmark's) and nothing
    # it started is left.
    launcher.popen.send_signal(signal.SIGTERM)
    assert launcher.wait(10) == 0, launcher.describe()
    seen = [launcher.pid, *pids.values(), new_echo]
    assert [pid for pid in seen if pid_alive(pid)] == [], f"left running: {seen}"
    wait_until(lambda: not live_names(session, keys), 5, "the nodes' liveliness tokens to go")


# Each bad file has a valid node first: a launcher that started nodes before validating would start it.
BAD_PIPELINES = {
    "unknown kind": ('[nodes.echo]\nkind = "echo"\n\n[nodes.track]\nkind = "teleport"\n',
                     ["nodes.track", "unknown node kind 'teleport'"]),
    "bad parameter value": ('[nodes.echo]\nkind = "echo"\n\n[nodes.cam]\nkind = "capture"\nfps = -5\n',
                            ["nodes.cam.fps", "greater than or equal to 0"]),
    "unknown parameter": ('[nodes.echo]\nkind = "echo"\n\n[nodes.cam]\nkind = "capture"\nfsp = 30\n',
                          ["nodes.cam.fsp", "Extra inputs are not permitted"]),
    "bad toml": ('[nodes.echo]\nkind = "echo"\n\n[nodes.cam\nkind = "capture"\n', ["not valid TOML", "line 4"]),
    "unknown top-level key": ('[nodes.echo]\nkind = "echo"\n\n[extras]\nanswer = 42\n',
                              ["extras", "Extra inputs are not permitted"]),
    "unknown bus key": ('[bus]\nrigg = "x"\n\n[nodes.echo]\nkind = "echo"\n', ["bus.rigg"]),
    "no nodes": ('[bus]\nrig = "x"\n', ["nodes", "Field required"]),
}

SPY = """\
import os
if os.environ.get("ARTRACK_SPY_DIR"):
    with open("/proc/self/cmdline", "rb") as f:
        cmd = f.read().replace(b"\\0", b" ")
    with open(os.path.join(os.environ["ARTRACK_SPY_DIR"], str(os.getpid())), "wb") as f:
        f.write(cmd)
"""


@pytest.mark.parametrize("case", sorted(BAD_PIPELINES))
def test_bad_pipeline_is_refused_before_anything_starts(bus, procs, tmp_path, case):
    text, expected = BAD_PIPELINES[case]
    path = tmp_path / "bad.toml"
    path.write_text(text)
    # A sitecustomize that records the command line of every Python process started below.
    spy, seen = tmp_path / "spy", tmp_path / "seen"
    spy.mkdir()
    seen.mkdir()
    (spy / "sitecustomize.py").write_text(SPY)
    done = procs.run("up", str(path), timeout=30, env={"PYTHONPATH": str(spy), "ARTRACK_SPY_DIR": str(seen)})

    assert done.poll() not in (None, 0)
    lines = [line for line in done.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, f"expected one error line, got:\n{done.stderr}"
    assert "ERROR" in lines[0] and str(path) in lines[0]
    for text in expected:
        assert text in lines[0], f"{text!r} missing from: {lines[0]}"
    assert done.stdout == ""
    started = [p.read_text() for p in seen.iterdir()]
    assert len(started) == 1 and " up " in started[0], f"processes started: {started}"


def test_up_refuses_a_nodes_own_calibration_made_for_other_frames_before_anything_starts(procs, tmp_path):
    """A pipeline file's replay tells the size of the frames it will send (the recording's first image of each
    camera it replays), and a node's own calibration file is held against it before any process starts."""
    calib, path = tmp_path / "hd.yaml", tmp_path / "hd.toml"
    K = np.array([[900.0, 0.0, 639.5], [0.0, 900.0, 359.5], [0.0, 0.0, 1.0]])
    write_camera_info(calib, CameraModel("cam0", 1280, 720, K, np.zeros(5), np.eye(4)))
    path.write_text(f'[nodes.replay]\nkind = "replay"\npath = "{ROOT / "recordings" / "markers.mcap"}"\n'
                    'keys = ["cam0/image"]\n\n'
                    f'[nodes.marker]\nkind = "marker_pose"\nmarker_length = 0.05\ncalib = "{calib}"\n')
    done = procs.run("up", str(path))
    assert done.poll() == 2, done.describe()
    lines = [line for line in done.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, done.stderr
    assert (f"ERROR artrack: {path}: nodes.marker: {calib}: calibrated for 1280x720, the frames are 640x480 "
            "(another aspect ratio)") in lines[0], done.stderr
