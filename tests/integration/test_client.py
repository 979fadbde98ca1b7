"""The client library against a real marker pipeline: poses, callbacks, queries, presence."""

from __future__ import annotations

import asyncio
import re
import signal
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from protocol.message import Header
from protocol.poses import Pose
from protocol.sensors import CameraInfo
from services.bus.discovery import client_states
from services.bus.pubsub import Inbox, Publisher, Role
from services.client import BusError, BusSettings, Client, connect
from tests.integration.support import START_S, collect, start_node, wait_live, wait_until

pytestmark = pytest.mark.integration

ROOT = Path(__file__).resolve().parents[2]
EXAMPLE = ROOT / "examples" / "track_marker.py"
LENGTH = 0.05


def start_pipeline(procs, session, keys) -> None:
    """A looping synthetic marker camera and a marker node, as two processes."""
    capture = start_node(procs, "capture", "cam", source=["synthetic:markers"], fps=30, loop=True)
    marker = start_node(procs, "marker_pose", "marker", camera="cam0", marker_length=LENGTH)
    wait_live(session, keys, {"cam", "marker"}, (capture, marker))


def client_for(bus, **options) -> Client:
    return Client(BusSettings(connect=(bus.endpoint,), rig=bus.rig), **options)


def test_the_example_app_prints_marker_poses_with_their_latency(bus, procs, session):
    start_pipeline(procs, session, bus.keys)
    app = procs.start([sys.executable, str(EXAMPLE), "cam0/**", "--count", "20"], name="example")
    assert app.wait(START_S) == 0, app.describe()
    pattern = re.compile(r"(cam0/marker/\d+) frame (\d+): (tracking|predicted|lost) t = \(([-+.\d]+), ([-+.\d]+), "
                         r"([-+.\d]+)\) m, latency ([.\d]+) ms")
    rows = [pattern.fullmatch(line) for line in app.stdout.splitlines()]
    assert len(rows) == 20 and all(rows), app.stdout
    tracked = [row for row in rows if row[3] == "tracking"]
    assert len(tracked) >= 15, app.stdout  # a marker at the edge of the view may be lost a frame
    depths = [float(row[6]) for row in tracked]
    latencies = [float(row[7]) for row in rows]
    assert all(0.05 < z < 5.0 for z in depths), depths  # the scene's camera stays 0.2-2 m from its board
    assert all(0.0 < ms < 2000.0 for ms in latencies), latencies


def test_ctrl_c_stops_the_example_app_quietly(bus, procs, session):
    start_pipeline(procs, session, bus.keys)
    app = procs.start([sys.executable, str(EXAMPLE), "cam0/**"], name="example")
    wait_until(lambda: "frame" in app.stdout, START_S, "the app's first pose")
    app.popen.send_signal(signal.SIGINT)
    assert app.wait(START_S) == 0, app.describe()
    assert "Traceback" not in app.stderr and "KeyboardInterrupt" not in app.stderr, app.stderr


def test_iterators_callbacks_latest_and_queries(bus, procs, session):
    start_pipeline(procs, session, bus.keys)
    infos = Inbox(session, bus.keys.camera_info("cam0"), CameraInfo, Role.RESULT)
    with client_for(bus, app="checks") as ar:
        got_back: list = []
        feed = ar.on_pose("cam0/*/*", got_back.append)
        with ar.poses("cam0/**", idle_timeout_s=START_S) as stream:
            updates = [next(stream) for _ in range(10)]
        assert all(u.target.startswith("cam0/marker/") and u.pose.child_frame_id for u in updates)
        assert [u.received_ns for u in updates] == sorted(u.received_ns for u in updates)
        assert all(0 < u.latency_ms < 2000 for u in updates)

        newest = ar.latest(updates[0].target, timeout_s=START_S)
        assert newest is not None and newest.target == updates[0].target

        assert len(asyncio.run(_take(ar, 5))) == 5
        wait_until(lambda: len(got_back) >= 5, START_S, "five callbacks")
        feed.close()

        assert {"cam", "marker"} <= {name for rig, name in ar.services() if rig == bus.rig}
        assert {"cam", "marker"} <= {name for rig, name in ar.status() if rig == bus.rig}
        published = collect(infos, 1)[0]
        answered = ar.calibration("cam0")
        assert answered is not None and np.allclose(answered.k, published.k) and answered.width == published.width
        assert ar.calibration("cam7", timeout_s=0.5) is None

        seen = client_states(session, bus.keys, 2.0)
        state = seen[(bus.rig, ar.id)]
        assert state.app == "checks"
        by_key = {s.key: s for s in state.subscriptions}
        latest_key = bus.keys.pose_pattern(updates[0].target)
        assert by_key[latest_key].received >= 1 and by_key[latest_key].last_stamp_ns is not None
    assert (bus.rig, ar.id) not in client_states(session, bus.keys, 1.0)


async def _take(ar: Client, n: int) -> list:
    """The first ``n`` poses of the rig through the asyncio stream."""
    got = []
    async with ar.poses_async("**", idle_timeout_s=START_S) as stream:
        async for update in stream:
            got.append(update)
            if len(got) == n:
                break
    return got


def test_a_target_nobody_publishes_gives_an_empty_stream_not_a_hang(bus, procs, session):
    start_pipeline(procs, session, bus.keys)
    with client_for(bus) as ar:
        started = time.monotonic()
        assert list(ar.poses("cam9/nothing", idle_timeout_s=1.0)) == []
        assert ar.latest("cam9/nothing", timeout_s=0.5) is None
        assert time.monotonic() - started < 10.0
        state = client_states(session, bus.keys, 2.0)[(bus.rig, ar.id)]
        waiting = {s.key: s.received for s in state.subscriptions}
        assert waiting == {bus.keys.pose("cam9/nothing"): 0}


def test_garbage_on_a_pose_key_is_counted_and_the_stream_goes_on(bus, session):
    key = bus.keys.pose("cam0/marker/1")
    with client_for(bus) as ar, ar.poses("cam0/**", idle_timeout_s=1.0) as stream:
        publisher = Publisher(session, key, Pose, Role.RESULT)
        wait_until(publisher.matched, START_S, "the client's subscriber")
        session.put(key, b"\x00garbage")  # another priority than the pose's: the two may arrive in either order
        publisher.put(Pose(header=Header(stamp_ns=time.time_ns(), seq=7), child_frame_id="marker_1"))
        update = next(stream)
        assert update.pose.header.seq == 7 and update.target == "cam0/marker/1"
        publisher.put(Pose(header=Header(stamp_ns=time.time_ns(), seq=8), child_frame_id="marker_1"))
        assert next(stream).pose.header.seq == 8
        wait_until(lambda: stream.state().received == 3, START_S, "all three payloads to arrive")
        assert list(stream) == []  # what is left (the garbage, if it came last) is skipped
        assert stream.state().decode_errors == 1


def test_a_slow_reader_drops_the_oldest_poses_and_counts_them(bus, session):
    key = bus.keys.pose("cam0/marker/2")
    with client_for(bus) as ar, ar.poses("cam0/marker/2", idle_timeout_s=2.0, depth=3) as stream:
        publisher = Publisher(session, key, Pose, Role.RESULT)
        wait_until(publisher.matched, START_S, "the client's subscriber")
        for seq in range(10):
            publisher.put(Pose(header=Header(stamp_ns=time.time_ns(), seq=seq), child_frame_id="marker_2"))
        wait_until(lambda: stream.state().received == 10, START_S, "ten poses")
        assert [u.pose.header.seq for u in stream] == [7, 8, 9]
        assert stream.dropped == 7


def test_a_client_whose_router_is_down_gets_one_clear_error(unused_endpoint):
    with pytest.raises(BusError, match=re.escape(unused_endpoint)):
        connect(mode="client", connect=unused_endpoint)
