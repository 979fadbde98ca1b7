"""The compose rig without Docker: its services' commands and environment run as they are (client
mode, rig0), with only the router's address swapped for this test's router and, for the recorder,
its volume for a temporary folder."""

from __future__ import annotations

import json
import os
import signal

import pytest

from protocol.poses import Pose
from protocol.tracking_state import TrackingState
from services.bus.pubsub import Inbox, Role
from services.bus.session import BusConfig
from tests.deploy_files import artrack_services, host_pipeline, instruction
from tests.integration.support import START_S, collect, states, wait_until

pytestmark = pytest.mark.integration


def composed_environment(service: dict, endpoint: str) -> dict[str, str]:
    """A compose service's environment, its router (``tcp/zenoh:7447``) replaced by ``endpoint``."""
    environment = {key: str(value) for key, value in service["environment"].items()}
    environment["ARTRACK_CONNECT"] = endpoint
    return environment


def test_the_compose_capture_and_marker_services_track_markers_through_the_router(bus, procs, session):
    services = artrack_services()
    environment = composed_environment(services["capture"], bus.endpoint)
    poses = Inbox(session, BusConfig.from_env(environment).keys.poses(), Pose, Role.RESULT)
    for name in ("capture", "marker"):
        verb, pipeline = services[name]["command"]
        procs.artrack(verb, str(host_pipeline(pipeline)), name=name, env=composed_environment(services[name],
                                                                                               bus.endpoint))

    tracked = collect(poses, lambda got: any(p.state == TrackingState.TRACKING for p in got))
    assert any(p.header.frame_id == "cam0" for p in tracked)
    healthcheck = json.loads(instruction("HEALTHCHECK")[-1].partition(" CMD ")[2])
    check = procs.artrack(*healthcheck[1:], name="healthcheck", env=composed_environment(services["marker"],
                                                                                          bus.endpoint))
    assert check.wait(START_S) == 0, check.describe()


def test_the_compose_recorder_starts_new_files_when_its_node_is_restarted(bus, procs, session, tmp_path):
    recorder = artrack_services()["recorder"]
    environment = composed_environment(recorder, bus.endpoint)
    keys = BusConfig.from_env(environment).keys
    volume = recorder["volumes"][0].split(":")[1]
    folder = tmp_path / "recordings"
    folder.mkdir()
    verb, pipeline = recorder["command"]
    local = tmp_path / "recorder.toml"
    local.write_text(host_pipeline(pipeline).read_text().replace(volume, str(folder)))
    procs.artrack(verb, str(local), name="recorder", env=environment)

    first = wait_until(lambda: states(session, keys).get("recorder"), START_S, "the recorder to answer")
    wait_until(lambda: list(folder.glob("rig-*_000.mcap")), START_S, "the recorder's first file")
    os.kill(first.pid, signal.SIGKILL)
    wait_until(lambda: (s := states(session, keys).get("recorder")) and s.pid != first.pid, START_S,
               "the recorder to come back with a new pid")
    wait_until(lambda: len(list(folder.glob("rig-*_000.mcap"))) == 2, START_S, "a second recording file")
