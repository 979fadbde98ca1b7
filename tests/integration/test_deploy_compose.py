"""The compose rig without Docker: its capture and marker services' commands and environment,
run as they are (client mode, rig0), with only the router's address swapped for this test's."""

from __future__ import annotations

import pytest

from protocol.poses import Pose, TrackingState
from services.runtime.bus import BusConfig
from services.runtime.pubsub import Inbox, Role
from tests.deploy_files import artrack_services, host_pipeline
from tests.integration.support import collect

pytestmark = pytest.mark.integration


def test_the_compose_capture_and_marker_services_track_markers_through_the_router(bus, procs, session):
    services = artrack_services()
    environment = {key: str(value) for key, value in services["capture"]["environment"].items()}
    environment["ARTRACK_CONNECT"] = bus.endpoint  # what Docker's DNS gives for tcp/zenoh:7447
    keys = BusConfig.from_env(environment).keys
    poses = Inbox(session, keys.poses(), Pose, Role.RESULT)
    for name in ("capture", "marker"):
        verb, pipeline = services[name]["command"]
        procs.artrack(verb, str(host_pipeline(pipeline)), name=name, env=environment)

    tracked = collect(poses, lambda got: any(p.state == TrackingState.TRACKING for p in got))
    assert any(p.header.frame_id == "cam0" for p in tracked)
