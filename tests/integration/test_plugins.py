"""A node kind and a tracker declared only in tests/plugin_tracker run through `artrack run` and
`artrack up`, found through ARTRACK_PLUGINS: no edit to the command line or any table."""

from __future__ import annotations

import tomllib

import pytest
from mcap.reader import make_reader

from protocol import decode
from protocol.sensors import Image
from services.bus.pubsub import Inbox, Role

from .support import START_S, collect

pytestmark = pytest.mark.integration

PLUGIN = {"ARTRACK_PLUGINS": "tests.plugin_tracker"}


def test_the_plugin_is_listed_and_its_flags_generated(procs):
    trackers = procs.run("trackers", env=PLUGIN)
    kinds = procs.run("kinds", env=PLUGIN)
    helped = procs.run("run", "stride", "--help", env=PLUGIN)
    assert trackers.poll() == kinds.poll() == helped.poll() == 0, trackers.describe()
    assert "stride" in trackers.stdout and "every n-th frame" in trackers.stdout
    assert "stride" in kinds.stdout and "tests.plugin_tracker.stride_node" in kinds.stdout
    assert "--every EVERY" in helped.stdout and "relay one frame in this many" in helped.stdout


def test_a_plugin_tracker_runs_as_a_job_and_is_recorded(procs, tmp_path):
    out = tmp_path / "stride.mcap"
    job = procs.artrack("run", "stride", "--source", "synthetic:pattern", "--frames", "20", "--fps", "40",
                        "--every", "5", "--scene-option", "width=80", "--scene-option", "height=64",
                        "--record", str(out), name="job", env=PLUGIN)
    assert job.wait(3 * START_S) == 0, job.describe()
    with open(out, "rb") as f:
        relayed = [decode(m.data) for _, channel, m in make_reader(f).iter_messages()
                   if channel.topic.endswith("/cam0/stride")]
    assert [m.header.seq for m in relayed] == [0, 5, 10, 15]
    assert relayed[0].data.shape[:2] == (64, 80)


def test_a_saved_job_runs_under_up(procs, session, bus, tmp_path):
    path = tmp_path / "stride.toml"
    saved = procs.run("run", "stride", "--source", "synthetic:pattern", "--fps", "30", "--every", "3",
                      "--scene-option", "width=64", "--save-pipeline", str(path), env=PLUGIN)
    assert saved.poll() == 0, saved.describe()
    document = tomllib.loads(path.read_text())
    node = document["nodes"]["stride-cam0"]
    assert (node["kind"], node["every"], node["inputs"], node["outputs"]) == (
        "stride", 3, ["cam0/image"], ["cam0/stride"])
    assert document["nodes"]["capture"]["scene"] == {"width": 64}  # typed by the scene's option, not text

    relayed = Inbox(session, bus.keys.camera("cam0", "stride"), Image, Role.RESULT)
    daemon = procs.artrack("up", str(path), name="up", env=PLUGIN)
    seen = collect(relayed, 4)
    assert all(image.header.seq % 3 == 0 for image in seen), [image.header.seq for image in seen]
    assert daemon.poll() is None, daemon.describe()


def test_without_the_plugin_the_tracker_is_unknown_in_one_line(procs):
    job = procs.run("run", "stride", "--source", "synthetic:pattern")
    assert job.poll() == 2
    assert "unknown tracker 'stride' (known: capture, echo, features, marker, slam, stereo)" in job.stderr
    assert "Traceback" not in job.stderr


def test_a_plugin_package_that_does_not_exist_is_one_line(procs):
    job = procs.run("trackers", env={"ARTRACK_PLUGINS": "no_such_package_here"})
    assert job.poll() == 2
    assert "ARTRACK_PLUGINS" in job.stderr and "no_such_package_here" in job.stderr
    assert "Traceback" not in job.stderr
