"""The markers node as a real process behind a real capture node: every frame yields one detection message."""

import random

import cv2
import numpy as np
import pytest

from protocol import CameraInfo, GroundTruth
from protocol.detections import MarkerDetections
from services.bus.pubsub import Inbox, Role
from services.convert import camera_model, matrix_from_transform
from services.geometry.camera import project_points
from services.geometry.se3 import transform_points
from services.synthetic.plane import rectangle_corners

from .support import START_S, collect, start_node, states, wait_live, wait_until

pytestmark = pytest.mark.integration

FRAMES = 12


def decode_errors(session, keys) -> int:
    stats = states(session, keys).get("markers")
    return stats.decode_errors if stats else 0


def test_scene_frames_yield_the_visible_markers_at_their_true_corners(bus, procs, session):
    keys = bus.keys
    detections = Inbox(session, keys.markers("cam0"), MarkerDetections, Role.RESULT)
    truths = Inbox(session, keys.truth("cam0"), GroundTruth, Role.RESULT)
    infos = Inbox(session, keys.camera_info("cam0"), CameraInfo, Role.RESULT)
    try:
        node = start_node(procs, "markers", "markers", camera="cam0", marker_length=0.05, lengths={"4": 0.06},
                          depth=16)
        wait_live(session, keys, {"markers"}, [node])
        start_node(procs, "capture", "cam", source="synthetic:markers", frames=FRAMES, fps=10,
                   wait_for_subscriber=True)
        found = collect(detections, FRAMES)
        truth = {m.header.seq: m for m in collect(truths, FRAMES)}
        K = camera_model(collect(infos, 1)[0]).K
    finally:
        for inbox in (detections, truths, infos):
            inbox.close()

    assert [m.header.seq for m in found] == list(range(FRAMES))
    corners_m = rectangle_corners(0.05, 0.05)
    errors = []
    for message in found:
        assert message.header == truth[message.header.seq].header and message.dictionary == "DICT_4X4_50"
        visible = {int(t.child_frame.split("/")[1]): matrix_from_transform(t.transform)
                   for t in truth[message.header.seq].transforms}
        assert message.ids.tolist() == sorted(visible), message.header.seq
        for marker_id, corners in zip(message.ids, message.corners, strict=True):
            expected = project_points(transform_points(visible[int(marker_id)], corners_m), K)
            errors.append(np.abs(corners - expected).max())
        assert message.side_m.tolist() == pytest.approx([0.06 if i == 4 else 0.05 for i in message.ids])
        assert np.all((message.quality > 0.8) & (message.quality <= 1.0))
    assert len(errors) >= 2 * FRAMES and max(errors) < 1.0


def test_blank_frames_give_empty_messages_and_garbage_is_counted(bus, procs, session, tmp_path):
    keys = bus.keys
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50)
    blank = np.full((240, 320, 3), 230, np.uint8)
    with_marker = blank.copy()
    with_marker[60:180, 100:220] = cv2.cvtColor(cv2.aruco.generateImageMarker(dictionary, 7, 120), cv2.COLOR_GRAY2BGR)
    for i, picture in enumerate((blank, with_marker, blank)):
        cv2.imwrite(str(tmp_path / f"{i}.png"), picture)
    detections = Inbox(session, keys.markers("cam0"), MarkerDetections, Role.RESULT)
    node = start_node(procs, "markers", "markers", depth=8)
    wait_live(session, keys, {"markers"}, [node])
    raw = session.declare_publisher(keys.image("cam0"))
    try:
        wait_until(lambda: raw.matching_status.matching, START_S, "the markers node to subscribe to its input")
        raw.put(random.Random(3).randbytes(2048))
        wait_until(lambda: decode_errors(session, keys) == 1, START_S, "the decode error to be counted")
    finally:
        raw.undeclare()
    try:
        start_node(procs, "capture", "cam", source=f"images:{tmp_path}", fps=20, wait_for_subscriber=True)
        found = collect(detections, 3)
    finally:
        detections.close()

    assert [m.header.seq for m in found] == [0, 1, 2]
    assert [m.ids.tolist() for m in found] == [[], [7], []]
    empty = found[0]
    assert (empty.corners.shape, empty.quality.shape, empty.side_m.shape) == ((0, 4, 2), (0,), (0,))
    assert np.abs(found[1].corners[0] - np.array([[100, 60], [220, 60], [220, 180], [100, 180]]) + 0.5).max() < 1.0
    assert found[1].side_m.tolist() == [0.0]
    assert node.poll() is None, node.describe()
    stats = states(session, keys)["markers"]
    assert (stats.decode_errors, stats.published, stats.skipped) == (1, 3, {"decode_error": 1})


@pytest.mark.parametrize(("params", "reason"), [
    ({"dictionary": "DICT_4X4_5"}, "unknown marker dictionary 'DICT_4X4_5'"),
    ({"parameters": {"adaptiveThreshWinSize": 9}}, "unknown detector parameter 'adaptiveThreshWinSize'"),
    ({"lengths": {"60": 0.05}}, "marker id 60 is not in the dictionary"),
])
def test_bad_settings_exit_2_with_one_clear_line(procs, params, reason):
    node = start_node(procs, "markers", "markers", **params)
    assert node.wait(START_S) == 2, node.describe()
    errors = [line for line in node.stderr.splitlines() if "ERROR" in line]
    assert len(errors) == 1 and reason in errors[0], node.stderr
