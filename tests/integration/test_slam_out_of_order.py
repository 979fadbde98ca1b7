"""The slam node on frames out of order, over a real bus: a late frame and a repeated stamp are skipped and
counted while the map goes on; frames that step back by more than ``STEP_BACK_S`` start a new map."""

from __future__ import annotations

import pytest

from protocol.message import Header
from protocol.poses import Pose
from protocol.sensors import Image
from protocol.tracking_state import TrackingState
from services.bus.pubsub import Inbox, Publisher, Role
from services.calibration.camera_info import write_camera_info
from services.slam.system import STEP_BACK_S
from services.synthetic import make_scene
from tests.integration.support import START_S, collect, start_node, states, wait_live, wait_until

pytestmark = pytest.mark.integration

START_NS = 100_000_000_000
"""The first frame's stamp: room time 0 s is 100 s."""


def test_late_and_repeated_frames_are_skipped_and_a_step_far_back_starts_a_new_map(bus, procs, session, tmp_path):
    scene = make_scene("room")
    calib = tmp_path / "room.yaml"
    write_camera_info(calib, scene.cameras[0])
    keys = bus.keys
    poses = Inbox(session, keys.slam_pose("cam0"), Pose, Role.RESULT)
    frames = Publisher(session, keys.image("cam0"), Image, Role.RESULT)
    sent: list[int] = []

    def send(index: int, stamp_ns: int | None = None) -> Pose:
        seq = len(sent)
        stamp_ns = START_NS + round(scene.time_s(index) * 1e9) if stamp_ns is None else stamp_ns
        sent.append(stamp_ns)
        frames.put(Image(header=Header(stamp_ns=stamp_ns, frame_id="cam0", seq=seq), encoding="mono8",
                         data=scene.render(index).images["cam0"]))
        return next(p for p in collect(poses, lambda got: any(p.header.seq == seq for p in got))
                    if p.header.seq == seq)

    try:
        node = start_node(procs, "slam", "slam", calib=str(calib), depth=10, mapping="inline")
        wait_live(session, keys, {"slam"}, [node])
        wait_until(frames.matched, START_S, "the node to subscribe")
        index = 0
        while send(index).state is not TrackingState.TRACKING:
            index += 1
            assert index < 30, "the room never initialised"
        late, twice = send(index - 3), send(index, sent[-1])
        assert [(p.state, p.reason) for p in (late, twice)] == [(TrackingState.LOST, "out_of_order")] * 2
        assert send(index + 1).state is TrackingState.TRACKING  # the same map goes on
        restarted = send(index + 2, sent[-1] - round(2 * STEP_BACK_S * 1e9))
        assert (restarted.state, restarted.reason) == (TrackingState.INITIALISING, "new_reference")
        stats = wait_until(lambda: (s := states(session, keys).get("slam")) and s.processed == len(sent) and s,
                           START_S, f"the node to count {len(sent)} frames")
        assert node.poll() is None, node.describe()
        assert stats.skipped == {"out_of_order": 2}, stats.skipped
    finally:
        frames.close()
        poses.close()
