"""The keypoints node as a real process behind a real capture node: every frame yields its keypoints, the
same the algorithm finds in-process; a frame too small is counted and answered with an empty message."""

import cv2
import numpy as np
import pytest

from protocol import Image
from protocol.detections import Keypoints
from services.bus.pubsub import Inbox, Role
from services.detection.grey import as_grey8
from services.detection.keypoints.detector import KeypointDetector
from services.detection.keypoints.node import Params
from services.synthetic.texture import procedural_texture

from .support import START_S, collect, start_node, states, wait_live, wait_until

pytestmark = pytest.mark.integration

FRAMES = 6


def test_scene_frames_yield_the_keypoints_found_in_process(bus, procs, session):
    keys = bus.keys
    found = Inbox(session, keys.keypoints("cam0"), Keypoints, Role.RESULT)
    images = Inbox(session, keys.image("cam0"), Image, Role.RESULT)
    params = {"camera": "cam0", "method": "orb", "max_count": 300, "depth": 16}
    try:
        node = start_node(procs, "keypoints", "keypoints", flow={"lossless": True, "acks": True, "upstream": ["cam"]},
                          **params)
        wait_live(session, keys, {"keypoints"}, [node])
        start_node(procs, "capture", "cam", source="synthetic:planar_target", frames=FRAMES, fps=10,
                   flow={"lossless": True, "credits_from": ["keypoints"]})  # every frame, whatever the load
        messages = collect(found, FRAMES)
        frames = {m.header.seq: m for m in collect(images, FRAMES)}
    finally:
        found.close()
        images.close()

    assert [m.header.seq for m in messages] == list(range(FRAMES))
    detector = KeypointDetector(Params(**params).keypoints)
    for message in messages:
        frame = frames[message.header.seq]
        expected = detector.detect(as_grey8(frame.data))
        assert message.header == frame.header
        assert (message.method, message.descriptor_type, message.norm) == ("orb", "ORB", "hamming")
        assert 100 <= len(message.points) <= 300 and message.descriptors.shape == (len(message.points), 32)
        assert np.array_equal(message.points, expected.points)
        assert np.array_equal(message.descriptors, expected.descriptors)


def test_a_frame_too_small_is_counted_and_answered_empty(bus, procs, session, tmp_path):
    keys = bus.keys
    texture = procedural_texture(np.random.default_rng(1), 320, 240)
    for i, picture in enumerate((texture, texture[:40, :40], cv2.cvtColor(texture, cv2.COLOR_GRAY2BGR))):
        cv2.imwrite(str(tmp_path / f"{i}.png"), picture)
    found = Inbox(session, keys.keypoints("cam0"), Keypoints, Role.RESULT)
    node = start_node(procs, "keypoints", "keypoints", method="harris", descriptor="teblid", max_count=200, depth=8)
    wait_live(session, keys, {"keypoints"}, [node])
    try:
        start_node(procs, "capture", "cam", source=f"images:{tmp_path}", fps=20, wait_for_subscriber=True)
        messages = collect(found, 3)
    finally:
        found.close()

    assert [m.header.seq for m in messages] == [0, 1, 2]
    counts = [len(m.points) for m in messages]
    assert counts[0] == counts[2] == 200 and counts[1] == 0
    assert messages[1].descriptors.shape == (0, 32) and messages[0].descriptor_type == "TEBLID"
    assert node.poll() is None, node.describe()
    stats = wait_until(lambda: states(session, keys).get("keypoints"), START_S, "the node's state")
    assert (stats.published, stats.skipped) == (3, {"unusable_frame": 1})
    assert any("WARNING" in line and "a 40x40 frame is too small for keypoints" in line
               for line in node.stderr.splitlines()), node.stderr


def test_an_unknown_method_exits_2_with_one_clear_line(procs):
    node = start_node(procs, "keypoints", "keypoints", method="surf")
    assert node.wait(START_S) == 2, node.describe()
    errors = [line for line in node.stderr.splitlines() if "ERROR" in line]
    assert len(errors) == 1 and "method: Input should be 'orb', 'sift', 'akaze'" in errors[0], node.stderr
