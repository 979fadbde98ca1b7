"""The ``artrack`` command line against real nodes on a private router."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from protocol.message import Header
from services.cli import parser
from services.runtime.logs import NATIVE_LOGGER

from .support import START_S, json_lines, live_names, start_node, states, wait_live, wait_until

pytestmark = pytest.mark.integration

PATTERN = Path(__file__).resolve().parents[2] / "recordings" / "pattern.mcap"
SMALL_CAMERA = {"cameras": ["cam0"], "fps": 20, "scene": {"width": 64, "height": 64}}


def _subcommands() -> list[str]:
    action = next(a for a in parser()._actions if a.dest == "command")
    return sorted(action.choices)


def test_help_lists_every_subcommand():
    done = subprocess.run([sys.executable, "-m", "services.cli", "--help"], capture_output=True, text=True,
                          timeout=30)
    assert done.returncode == 0, done.stderr
    names = _subcommands()
    assert {"up", "router", "list", "echo", "demo", "node"} <= set(names)
    for name in names:
        assert re.search(rf"^\s+{name}\s+\S", done.stdout, re.MULTILINE), f"`artrack --help` does not list {name}"


def test_the_installed_command_and_the_example_run_from_outside_the_checkout(tmp_path):
    bin_dir = Path(sys.executable).parent  # the venv's bin/, where the README says `artrack` is
    version = subprocess.run([str(bin_dir / "artrack"), "--version"], capture_output=True, text=True, timeout=30,
                             cwd=tmp_path)
    assert version.returncode == 0 and version.stdout.startswith("artrack "), version.stderr
    example = Path(__file__).resolve().parents[2] / "examples" / "track_marker.py"
    helped = subprocess.run([sys.executable, str(example), "--help"], capture_output=True, text=True, timeout=30,
                            cwd=tmp_path)
    assert helped.returncode == 0 and "Follow tracked markers" in helped.stdout, helped.stderr


def test_list_shows_the_running_nodes_with_kind_and_pid(bus, procs, session):
    cam = start_node(procs, "capture", "cam", **SMALL_CAMERA)
    echo = start_node(procs, "echo", "relay", camera="cam0")
    wait_live(session, bus.keys, {"cam", "relay"}, [cam, echo])
    listed = procs.run("list", "--timeout", "1.5")
    assert listed.poll() == 0, listed.describe()
    rows = {}
    for line in listed.stdout.splitlines()[1:]:
        rig, name, kind, pid, *_ = line.split()
        rows[name] = (rig, kind, int(pid))
    assert rows == {"cam": (bus.rig, "capture", cam.pid), "relay": (bus.rig, "echo", echo.pid)}, listed.stdout
    assert listed.stdout.split()[:3] == ["RIG", "NODE", "KIND"]


def test_zenoh_log_lines_go_to_stderr_and_leave_json_output_whole(bus, procs):
    status = procs.run("status", "--timeout", "1", "--json", env={"RUST_LOG": "info"})
    assert "zenoh" in status.stderr  # Zenoh's own log lines were written, to stderr
    report = json.loads(status.stdout)  # stdout holds the JSON document alone
    assert report["healthy"] is False and report["pipelines"] == []


def test_with_json_logs_zenoh_log_lines_are_json_records_too(bus, procs):
    status = procs.run("--log-format", "json", "status", "--timeout", "1", "--json", env={"RUST_LOG": "info"})
    records = json_lines(status.stderr)  # every line on stderr is one JSON object, Zenoh's included
    native = [r for r in records if r["logger"] == NATIVE_LOGGER]
    assert native and {r["level"] for r in native} <= {"info", "warning", "error"}, status.stderr
    assert all("\x1b[" not in r["message"] for r in native)
    assert json.loads(status.stdout)["pipelines"] == []


def test_list_says_when_no_node_is_up(bus, procs):
    listed = procs.run("list", "--timeout", "0.5")
    assert listed.poll() == 0, listed.describe()
    assert listed.stdout == ""
    assert "no artrack nodes are up" in listed.stderr


def test_echo_prints_count_json_lines_with_schema_fields(bus, procs, session):
    cam = start_node(procs, "capture", "cam", **SMALL_CAMERA)
    wait_live(session, bus.keys, {"cam"}, [cam])

    images = procs.run("echo", "cam0/image", "--count", "3", "--timeout", str(START_S))
    assert images.poll() == 0, images.describe()
    lines = json_lines(images.stdout)
    assert len(lines) == 3, images.stdout
    for line in lines:
        assert line["key"] == bus.keys.image("cam0")
        assert (line["schema"], line["version"]) == ("artrack.Image", 1)
        assert line["encoding"] == "mono8"
        assert line["data"] == {"dtype": "uint8", "shape": [64, 64]}  # large arrays are summarised
        assert line["header"]["frame_id"] == "cam0" and line["header"]["stamp_ns"] > 0
    seqs = [line["header"]["seq"] for line in lines]
    assert seqs == sorted(set(seqs))

    infos = procs.run("echo", bus.keys.camera_info("cam0"), "--count", "2", "--timeout", str(START_S))
    assert infos.poll() == 0, infos.describe()
    lines = json_lines(infos.stdout)
    assert len(lines) == 2, infos.stdout
    for line in lines:
        assert (line["schema"], line["width"], line["height"]) == ("artrack.CameraInfo", 64, 64)
        assert len(line["k"]) == 9 and line["k"][8] == 1.0


def test_echo_shows_the_key_an_error_report_arrived_on_and_keeps_its_own(bus, procs, session):
    from protocol.system import ErrorReport
    from services.bus.pubsub import Publisher, Role

    echo = procs.artrack("echo", bus.keys.every_node("errors"), "--count", "1", "--timeout", str(START_S))
    arrival = bus.keys.errors("marker")
    report = ErrorReport(header=Header(stamp_ns=5), node="marker", kind="no_calibration", detail="no CameraInfo",
                         key=bus.keys.camera_info("cam0"))
    publisher = Publisher(session, arrival, ErrorReport, Role.RESULT)
    wait_until(lambda: publisher.matched() or echo.poll() is not None, START_S, "echo subscribed")
    wait_until(lambda: publisher.put(report) or echo.poll() is not None, START_S, "echo printed a line",
               interval_s=0.2)
    assert echo.wait(START_S) == 0, echo.describe()
    [line] = json_lines(echo.stdout)
    assert line["key"] == arrival and line["message_key"] == bus.keys.camera_info("cam0")
    assert (line["schema"], line["node"], line["kind"], line["detail"]) == (
        "artrack.ErrorReport", "marker", "no_calibration", "no CameraInfo")


def test_echo_says_when_nothing_arrived_before_its_timeout(bus, procs):
    quiet = procs.run("echo", "cam7/image", "--timeout", "1")
    assert quiet.poll() == 1 and quiet.stdout == "", quiet.describe()
    lines = [line for line in quiet.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].endswith(f"nothing arrived on {bus.keys.image('cam7')} in 1 s"), quiet.stderr


def test_echo_refuses_a_bad_key_expression_in_one_line(procs):
    refused = procs.run("echo", "a b//c", "--connect", "tcp/127.0.0.1:9", timeout=30)
    assert refused.poll() == 2, refused.describe()
    assert refused.stderr.count("\n") == 1, refused.stderr
    assert "key expression 'a b//c' is not valid: it has an empty segment" in refused.stderr


def test_demo_tracks_the_bundled_markers_and_scores_them(bus, procs, tmp_path):
    demo = procs.run("demo", "--runs", str(tmp_path), "--connect", bus.endpoint, timeout=120)
    assert demo.poll() == 0, demo.describe()
    summary = dict(re.findall(r"^\s*([a-z /0-9]+):\s+(.*)$", demo.stdout, re.MULTILINE))
    assert summary["frames"].startswith("150 of 150 replayed, 150 with ground truth, 150 with poses"), demo.stdout
    tracked, total = map(int, re.match(r"(\d+) of (\d+) marker views", summary["markers tracked"]).groups())
    assert total > 600 and tracked >= 0.99 * total, summary["markers tracked"]
    rotation = float(re.match(r"median ([0-9.]+) deg", summary["rotation error"]).group(1))
    range_pct = float(re.search(r"([0-9.]+) % of range", summary["translation error"]).group(1))
    assert rotation < 0.5 and range_pct < 1.0, demo.stdout
    p50 = float(summary["latency p50 / p99"].split()[0])
    assert 0 < p50 < 100, "restamped frames should give poses within milliseconds of their new stamp"
    run = Path(summary["recorded"]).parent
    assert run.parent == tmp_path and (run / "run.mcap").stat().st_size > 0 and (run / "run.rrd").stat().st_size > 0


def test_demo_names_a_missing_recording(procs, tmp_path):
    demo = procs.run("demo", "--recording", str(tmp_path / "none.mcap"), timeout=30)
    assert demo.poll() == 2 and "none.mcap: no such recording" in demo.stderr


@pytest.mark.parametrize("kind, params", [("echo", {"camera": "cam0"}), ("capture", SMALL_CAMERA)])
def test_node_stops_on_sigterm_and_leaves_the_bus(bus, procs, session, kind, params):
    node = start_node(procs, kind, "n1", **params)
    wait_live(session, bus.keys, {"n1"}, [node])
    wait_until(lambda: "n1" in states(session, bus.keys), START_S, "the node to answer its state query")
    os.kill(node.pid, signal.SIGTERM)
    assert node.wait(10) == 0, node.describe()  # a hang, not a slow stop: the time is the `stops` benchmark's
    assert "node n1 stopped" in node.stderr
    wait_until(lambda: "n1" not in live_names(session, bus.keys), 5, "the node's liveliness token to go")
    assert "n1" not in states(session, bus.keys)
