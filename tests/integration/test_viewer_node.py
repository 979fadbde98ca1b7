"""The viewer node as a real process on a real bus: what its .rrd holds, how it limits images, how it serves."""

from __future__ import annotations

import os
import signal
import socket
from pathlib import Path

import numpy as np
import pytest

from protocol import Header, MarkerDetections, Pose, Transform
from services.bus.pubsub import Publisher, Role
from services.synthetic import make_scene
from tests.viewer_contents import RrdContents

from .support import START_S, start_node, states, wait_live, wait_until

pytestmark = pytest.mark.integration

FRAMES, FPS, WIDTH, HEIGHT = 45, 30, 320, 240
RESULTS = 20
IMAGE_HZ = 10


def pose(i: int) -> Pose:
    return Pose(header=Header(stamp_ns=1_700_000_000_000_000_000 + i * 10_000_000, frame_id="cam0", seq=i),
                child_frame_id="marker/3", transform=Transform(translation=(0.01 * i, -0.1, 0.5 + 0.02 * i)))


def markers(i: int) -> MarkerDetections:
    return MarkerDetections(header=pose(i).header, dictionary="DICT_4X4_50", ids=np.array([3, 9], np.int32),
                            corners=np.full((2, 4, 2), float(i), np.float32), quality=np.ones(2, np.float32),
                            side_m=np.full(2, 0.05, np.float32))


def received(session, keys, node: str) -> dict[str, int]:
    """Messages ``node`` has received so far, by subscribed key expression."""
    found = states(session, keys).get(node)
    return {} if found is None else {s.key: s.messages for s in found.streams if s.direction == "in"}


def stop(proc) -> None:
    os.kill(proc.pid, signal.SIGINT)
    assert proc.wait(15) == 0, proc.describe()


def test_viewer_node_logs_what_the_rig_publishes_and_limits_images(bus, procs, session, tmp_path: Path):
    keys, out = bus.keys, tmp_path / "live.rrd"
    viewer = start_node(procs, "viewer", "viewer", rrd=str(out), image_hz=IMAGE_HZ)
    wait_live(session, keys, {"viewer"}, [viewer])
    capture = start_node(procs, "capture", "cam", source="synthetic:markers", fps=FPS, frames=FRAMES,
                         wait_for_subscriber=True, scene={"width": WIDTH, "height": HEIGHT})
    poses = Publisher(session, keys.pose("marker-3"), Pose, Role.RESULT)
    found = Publisher(session, keys.markers("cam0"), MarkerDetections, Role.RESULT)
    try:
        wait_until(lambda: poses.matched() and found.matched(), START_S, "the viewer to subscribe")
        for i in range(RESULTS):
            poses.put(pose(i))
            found.put(markers(i))
    finally:
        poses.close()
        found.close()
    assert capture.wait(START_S + FRAMES / FPS) == 0, capture.describe()
    image_key = f"{keys.prefix}/*/image"

    def every_result_in() -> dict[str, int] | None:
        counts = received(session, keys, "viewer")
        results = (counts.get(keys.poses()), counts.get(f"{keys.prefix}/*/markers"))
        return counts if results == (RESULTS, RESULTS) and counts.get(image_key) else None

    counts = wait_until(every_result_in, START_S, "the viewer to receive every result")
    stop(viewer)

    contents = RrdContents(out)
    images = contents.rows("world/cam0/image", "Image:buffer")
    slots = {row.times["stamp"] // (1_000_000_000 // IMAGE_HZ) for row in images}
    assert len(slots) == len(images), "two images logged in one 1/image_hz slot"
    assert 5 <= len(images) <= FRAMES * IMAGE_HZ / FPS + 1 < counts[image_key], (len(images), counts)
    scene = make_scene("markers", width=WIDTH, height=HEIGHT)
    last = images[-1]
    np.testing.assert_array_equal(last.numbers(), scene.render(last.times["seq"]).images["cam0"].ravel())
    (resolution,) = contents.rows("world/cam0/image", "Pinhole:resolution")
    assert resolution.numbers().tolist() == [WIDTH, HEIGHT]
    k = contents.rows("world/cam0/image", "Pinhole:image_from_camera")[0].numbers().reshape(3, 3).T
    np.testing.assert_allclose(k, scene.cameras[0].K, rtol=1e-6)
    assert any(entity.startswith("world/cam0/truth/marker/") for entity in contents.entities)

    moved = contents.rows("world/cam0/pose/marker/3", "Transform3D:translation")
    np.testing.assert_allclose([r.numbers() for r in moved], [pose(i).transform.translation for i in range(RESULTS)],
                               rtol=1e-6)
    labels = contents.rows("world/cam0/image/markers", "LineStrips2D:labels")
    assert len(labels) == RESULTS and labels[0].values.to_pylist() == ["3", "9"]
    assert f"stats/rate_hz/cam/out/{keys.prefix}/cam0/image" in contents.entities
    assert ("2D", "world/cam0/image") in contents.views()


def listening_addresses(port: int) -> set[str]:
    """IPv4 addresses with a socket listening on ``port`` (from /proc/net/tcp)."""
    found = set()
    for line in Path("/proc/net/tcp").read_text().splitlines()[1:]:
        local, state = line.split()[1], line.split()[3]
        address, at = local.split(":")
        if int(at, 16) == port and state == "0A":  # LISTEN
            found.add(socket.inet_ntoa(bytes.fromhex(address)[::-1]))
    return found


def test_viewer_node_serves_grpc_on_loopback_by_default(bus, procs, session, unused_endpoint):
    port = int(unused_endpoint.rsplit(":", 1)[1])
    viewer = start_node(procs, "viewer", "viewer", serve=True, port=port)
    wait_live(session, bus.keys, {"viewer"}, [viewer])
    wait_until(lambda: listening_addresses(port), START_S, "the gRPC server to listen")
    assert listening_addresses(port) == {"127.0.0.1"}
    socket.create_connection(("127.0.0.1", port), timeout=2).close()
    stop(viewer)
    assert "serving rerun+http://127.0.0.1:" in viewer.stderr
