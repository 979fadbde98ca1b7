"""Nodes composed into one process: messages by reference between them, on the bus only for other sessions,
and the same recording whether a node runs in its group or split out into its own process."""

from __future__ import annotations

import time

import numpy as np
import pytest
from mcap.reader import make_reader

import services.bus.pubsub as pubsub
from protocol import decode
from protocol.message import Header
from protocol.sensors import Image
from protocol.system import NodeStats
from services.bus.pubsub import Inbox, Role
from services.runtime.host import Host
from services.runtime.node import Node
from tests.integration.support import START_S, collect, wait_until

pytestmark = pytest.mark.integration


def _image(seq: int) -> Image:
    pixels = np.full((48, 64), seq, np.uint8)
    return Image(header=Header(stamp_ns=time.time_ns(), seq=seq, frame_id="cam0"), encoding="mono8", data=pixels)


def test_nodes_of_one_process_pass_messages_by_reference_and_encode_only_for_another_session(bus, session,
                                                                                             monkeypatch):
    encoded: list[str] = []
    real_encode = pubsub.encode
    monkeypatch.setattr(pubsub, "encode", lambda message: encoded.append(message.SCHEMA) or real_encode(message))
    host = Host(bus.config)
    try:
        with Node("maker", "test", bus.config, host=host) as maker, \
                Node("taker", "test", bus.config, host=host) as taker:
            out = maker.publisher(bus.keys.image("cam0"), Image, Role.FRAME)
            frames = taker.inbox(bus.keys.image("cam0"), Image, Role.FRAME, depth=10)
            first = _image(0)
            out.put(first)
            assert frames.take().message is first  # the very object: no encode, no copy, no decode
            assert encoded == [] and out.matched() and not out.raw.wanted()

            outside = Inbox(session, bus.keys.image("cam0"), Image, Role.FRAME, depth=10)
            wait_until(out.raw.wanted, START_S, "the publisher to see the other session's subscriber")
            second = _image(1)
            out.put(second)
            assert frames.take().message is second
            [arrived] = collect(outside, 1)
            assert arrived == second and arrived is not second
            assert encoded == ["artrack.Image"]  # once, for the bus
            assert frames.take() is None  # and not a second time through Zenoh
            outside.close()
            assert out.counter.messages == 2 and frames.counter.messages == 2
    finally:
        host.close()


def _pipeline(tmp_path, out, process: str) -> str:
    path = tmp_path / f"{process or 'apart'}.toml"
    path.write_text(f"""
[nodes.cam]
kind = "capture"
source = "synthetic:pattern"
cameras = ["cam0"]
fps = 60
frames = 30
process = "camera"

[nodes.echo]
kind = "echo"
camera = "cam0"
{f'process = "{process}"' if process else ''}

[nodes.rec]
kind = "recorder"
out = "{out}"
""")
    return str(path)


def _recorded(path) -> tuple[dict[str, list], dict[str, int]]:
    """The images and echoes recorded, by stream; each node's pid from its last recorded stats."""
    streams: dict[str, list] = {"image": [], "echo": []}
    pids: dict[str, int] = {}
    with open(path, "rb") as f:
        for _, channel, message in make_reader(f).iter_messages():
            stream = channel.topic.rsplit("/", 1)[-1]
            if stream in streams:
                streams[stream].append(decode(message.data))
            elif stream == "stats":
                stats = decode(message.data)
                assert isinstance(stats, NodeStats)
                pids[stats.node] = stats.pid
    return streams, pids


def test_a_group_beside_a_recorder_records_what_separate_processes_record(procs, tmp_path):
    runs = {}
    for process in ("camera", ""):
        out = tmp_path / f"{process or 'apart'}.mcap"
        job = procs.run("run", _pipeline(tmp_path, out, process), "--quiet", timeout=6 * START_S)
        assert job.poll() == 0, job.describe()
        runs[process] = _recorded(out)
    (grouped, grouped_pids), (apart, apart_pids) = runs["camera"], runs[""]
    for streams in (grouped, apart):
        assert [m.header.seq for m in streams["image"]] == list(range(30))
        assert [m.header.seq for m in streams["echo"]] == list(range(30))
        assert all(np.array_equal(e.data, i.data) for e, i in zip(streams["echo"], streams["image"], strict=True))
    assert [m.data.tobytes() for m in grouped["echo"]] == [m.data.tobytes() for m in apart["echo"]]
    assert grouped_pids["cam"] == grouped_pids["echo"] != grouped_pids["rec"]
    assert len(set(apart_pids.values())) == 3


def test_a_member_that_cannot_run_stops_its_group_and_the_job_says_which_and_why(procs, tmp_path):
    path, empty = tmp_path / "broken.toml", tmp_path / "empty"
    empty.mkdir()  # a folder passes the job's checks; the node finds no image in it
    path.write_text(f"""
[nodes.cam]
kind = "capture"
source = "images:{empty}"
cameras = ["cam0"]
process = "camera"

[nodes.echo]
kind = "echo"
camera = "cam0"
process = "camera"
""")
    job = procs.run("run", str(path), "--quiet", timeout=4 * START_S)
    assert job.poll() == 2, job.describe()
    last = job.stderr.strip().splitlines()[-1]
    assert f"source camera ended with code 2: node cam: images:{empty}: no image files in {empty} (" in last, last


def test_the_stereo_template_tracks_alike_grouped_and_split(procs, tmp_path):
    """The template's grouping (source and blobs in one process) and every node apart give the same poses (the
    scene's own stamps: the bodies' motion is predicted from them, so wall-clock stamps would differ by run)."""
    runs = {}
    for layout in ("given", "separate"):
        out = tmp_path / f"{layout}.mcap"
        job = procs.run("run", "stereo", "--source", "synthetic:ir_rig", "--frames", "40", "--stamps", "source",
                        "--record", str(out), "--processes", layout, "--quiet", timeout=6 * START_S)
        assert job.poll() == 0, job.describe()
        poses: dict[str, list] = {}
        pids: dict[str, int] = {}
        with open(out, "rb") as f:
            for _, channel, message in make_reader(f).iter_messages():
                if "/pose/" in channel.topic:
                    pose = decode(message.data)
                    poses.setdefault(channel.topic.rsplit("/pose/", 1)[1], []).append(
                        (pose.header.seq, pose.state, pose.transform, pose.covariance))
                elif channel.topic.endswith("/stats"):
                    stats = decode(message.data)
                    pids[stats.node] = stats.pid
        runs[layout] = poses, pids
    (grouped, grouped_pids), (apart, apart_pids) = runs["given"], runs["separate"]
    assert grouped_pids["capture"] == grouped_pids["blobs-cam0"] == grouped_pids["blobs-cam1"] != grouped_pids["bodies"]
    assert len(set(apart_pids.values())) == len(apart_pids) == 5  # the recorder too
    assert set(grouped) == {"body/head", "body/tool", "body/wand"} and len(grouped["body/wand"]) >= 30
    assert grouped == apart
