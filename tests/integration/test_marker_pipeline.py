"""The marker pipeline as real processes: frames in, poses out, scored against ground truth."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import yaml
from mcap.reader import make_reader

from protocol import decode
from protocol.detections import MarkerDetections
from protocol.message import Header
from protocol.poses import Pose
from protocol.tracking_state import TrackingState
from services.bus.pubsub import Inbox, Publisher, Role
from services.calibration.camera_info import write_camera_info
from services.convert import matrix_from_transform
from services.estimation.markers.map import grid_map
from services.geometry.camera import project_points
from services.geometry.evaluation import pose_error
from services.geometry.se3 import invert, transform_points
from services.synthetic import make_scene
from tests.integration.support import START_S, collect, start_node, states, wait_live, wait_until
from tests.viewer_contents import RrdContents

pytestmark = pytest.mark.integration

LENGTH = 0.05
BOARD = {"name": "board", "dictionary": "DICT_4X4_50",
         "grid": {"columns": 3, "rows": 2, "length": LENGTH, "separation": LENGTH, "first_id": 0}}
"""The ``markers`` scene's default board: 6 markers, 3 by 2, centres two lengths apart."""


def recorded(path) -> dict[str, list]:
    """Every decoded message of an MCAP file by its key, in log order."""
    found: dict[str, list] = {}
    with open(path, "rb") as f:
        for _, channel, message in make_reader(f).iter_messages(log_time_order=True):
            found.setdefault(channel.topic, []).append(decode(message.data))
    return found


def truth_by_frame(messages: list) -> dict[int, dict[str, np.ndarray]]:
    return {m.header.seq: {t.child_frame: matrix_from_transform(t.transform) for t in m.transforms}
            for m in messages}


def errors(poses: list[Pose], truth: dict[int, dict[str, np.ndarray]], child_of=lambda pose: pose.child_frame_id):
    """(rotation deg, translation % of range) of each tracking pose against its frame's truth."""
    rows = []
    for pose in poses:
        T_true = truth[pose.header.seq][child_of(pose)]
        rotation, translation = pose_error(matrix_from_transform(pose.transform), T_true)
        rows.append((np.degrees(rotation), 100 * translation / np.linalg.norm(T_true[:3, 3])))
    return np.array(rows)


def test_marker_job_tracks_every_visible_marker_records_exports_and_views(procs, tmp_path):
    out, rrd = tmp_path / "job.mcap", tmp_path / "job.rrd"
    job = procs.artrack("run", "marker", "--source", "synthetic:markers", "--frames", "30", "--fps", "30",
                        "--marker-length", str(LENGTH), "--record", str(out), "--rerun", str(rrd), name="job")
    assert job.wait(4 * START_S) == 0, job.describe()
    messages = recorded(out)
    prefix = next(key for key in messages if key.endswith("/cam0/image")).removesuffix("/cam0/image")
    detections = messages[f"{prefix}/cam0/markers"]
    seen = [d.header.seq for d in detections]  # one message per frame handled, empty or not
    dropped = messages[f"{prefix}/node/marker-cam0/stats"][-1].dropped  # frames replaced while busy (latest-wins)
    assert seen == sorted(set(seen)) and len(seen) + dropped == 30 and len(seen) >= 25, (seen, dropped)
    truth = truth_by_frame(messages[f"{prefix}/cam0/truth"])
    poses = [p for key, ms in messages.items() if key.startswith(f"{prefix}/pose/cam0/marker/") for p in ms]
    tracking = [p for p in poses if p.state is TrackingState.TRACKING]
    views = {(seq, child) for seq, known in truth.items() for child in known}
    assert {(p.header.seq, p.child_frame_id) for p in tracking} >= {v for v in views if v[0] in seen}
    table = errors(tracking, truth)
    assert np.median(table[:, 0]) < 0.5 and np.median(table[:, 1]) < 1.0, np.median(table, axis=0)
    assert all(p.quality.inliers == 4 and p.quality.reprojection_rms_px < 1.0 for p in tracking)
    assert all(p.covariance is not None and np.all(np.diag(np.reshape(p.covariance, (6, 6))) > 0) for p in tracking)

    key = f"{prefix}/pose/cam0/marker/0"
    tum = procs.run("export", str(out), "--key", key, "--format", "tum", "--out", str(tmp_path / "m0.tum"))
    assert tum.poll() == 0, tum.describe()
    lines = (tmp_path / "m0.tum").read_text().split("\n")
    rows = [line.split() for line in lines if line]
    marker0 = [p for p in tracking if p.child_frame_id == "marker/0"]
    assert len(rows) == len(marker0) and all(len(row) == 8 for row in rows)
    assert np.allclose([[float(v) for v in row[1:4]] for row in rows],
                       [p.transform.translation for p in marker0])

    contents = RrdContents(rrd)
    assert contents.rows("world/cam0/pose/marker/0", "Transform3D:translation")
    assert contents.rows("world/cam0/image/markers", "LineStrips2D:strips")


def test_a_board_gives_one_pose_from_all_its_markers(procs, tmp_path):
    board, out = tmp_path / "board.yaml", tmp_path / "job.mcap"
    board.write_text(yaml.safe_dump(BOARD))
    job = procs.artrack("run", "marker", "--source", "synthetic:markers", "--frames", "20", "--fps", "30",
                        "--board", str(board), "--record", str(out), name="job")
    assert job.wait(4 * START_S) == 0, job.describe()
    messages = recorded(out)
    prefix = next(key for key in messages if key.endswith("/cam0/image")).removesuffix("/cam0/image")
    assert not any(key.startswith(f"{prefix}/pose/cam0/marker/") for key in messages)  # the board's own markers
    poses = [p for p in messages[f"{prefix}/pose/cam0/board"] if p.state is TrackingState.TRACKING]
    assert len(poses) == 20 and all(p.quality.inliers >= 8 for p in poses)
    T_board_marker0 = grid_map("board", 3, 2, LENGTH, LENGTH).markers[0].T_map_marker
    truth = {seq: {"board": known["marker/0"] @ invert(T_board_marker0)}
             for seq, known in truth_by_frame(messages[f"{prefix}/cam0/truth"]).items() if "marker/0" in known}
    scored = [p for p in poses if p.header.seq in truth]
    table = errors(scored, truth)
    assert len(scored) >= 15 and np.median(table[:, 0]) < 0.3 and np.median(table[:, 1]) < 0.5, table


def rendered_frames(tmp_path, count: int):
    """``count`` frames of the markers scene as PNG files, the scene's camera, and its truth per frame."""
    scene = make_scene("markers")
    camera = scene.cameras[0]
    folder = tmp_path / "frames"
    folder.mkdir()
    truth = {}
    for i in range(count):
        frame = scene.render(i)
        cv2.imwrite(str(folder / f"{i:04d}.png"), frame.images[camera.name])
        truth[i] = {child: T for _, child, T in frame.truth[camera.name]}
    return folder, camera, truth


def test_an_uncalibrated_camera_gives_detections_and_a_no_calibration_state(bus, procs, session, tmp_path):
    folder, _, _ = rendered_frames(tmp_path, 4)
    keys = bus.keys
    poses = Inbox(session, keys.poses(), Pose, Role.RESULT)
    markers = Inbox(session, keys.markers("cam0"), MarkerDetections, Role.RESULT)
    try:
        node = start_node(procs, "marker_pose", "marker", marker_length=LENGTH)
        wait_live(session, keys, {"marker"}, [node])
        start_node(procs, "capture", "cam", source=f"images:{folder}", fps=10, wait_for_subscriber=True)
        got = collect(poses, lambda got: {p.header.seq for p in got} >= {0, 1, 2, 3})
        assert {p.state for p in got} == {TrackingState.NO_CALIBRATION}
        found = collect(markers, lambda got: len(got) >= 4)
        assert all(len(d.ids) >= 4 for d in found)
        assert {p.child_frame_id for p in got if p.header.seq == 0} == {f"marker/{i}" for i in found[0].ids}
        stats = wait_until(lambda: states(session, keys).get("marker"), START_S, "the node's state")
        assert stats.skipped.get("no_calibration", 0) >= 4
        assert "no CameraInfo for cam0" in node.stderr
    finally:
        poses.close()
        markers.close()


@pytest.mark.parametrize("source", ["images", "video"])
def test_a_calibrated_file_source_gives_accurate_poses(bus, procs, session, tmp_path, source):
    folder, camera, truth = rendered_frames(tmp_path, 8)
    calib = tmp_path / "cam0.yaml"
    write_camera_info(calib, camera)
    uri = f"images:{folder}"
    if source == "video":
        video = tmp_path / "markers.avi"
        writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 10, (camera.width, camera.height))
        for path in sorted(folder.iterdir()):
            writer.write(cv2.imread(str(path)))
        writer.release()
        uri = f"video:{video}"
    poses = Inbox(session, bus.keys.poses(), Pose, Role.RESULT)
    try:
        node = start_node(procs, "marker_pose", "marker", marker_length=LENGTH,
                          flow={"lossless": True, "acks": True, "upstream": ["cam"]})
        wait_live(session, bus.keys, {"marker"}, [node])
        start_node(procs, "capture", "cam", source=uri, calib=[str(calib)], fps=10,
                   flow={"lossless": True, "credits_from": ["marker"]})  # every frame, whatever the load
        seen = {(s, c) for s, k in truth.items() for c in k}
        # A frame's poses are put one by one: wait for every target's, not for the frame's first.
        got = collect(poses, lambda got: {(p.header.seq, p.child_frame_id) for p in got} >= seen)
        tracking = [p for p in got if p.state is TrackingState.TRACKING]
        assert {(p.header.seq, p.child_frame_id) for p in tracking} >= seen
        table = errors(tracking, truth)
        limit = 0.5 if source == "images" else 1.5  # MJPG compresses the corners' edges
        assert np.median(table[:, 0]) < limit and np.median(table[:, 1]) < 1.0, np.median(table, axis=0)
    finally:
        poses.close()


def test_bad_detections_are_counted_and_the_node_goes_on(bus, procs, session, tmp_path):
    scene = make_scene("markers")
    camera = scene.cameras[0]
    calib = tmp_path / "cam0.yaml"
    write_camera_info(calib, camera)
    keys = bus.keys
    poses = Inbox(session, keys.poses(), Pose, Role.RESULT)
    out = Publisher(session, keys.markers("cam0"), MarkerDetections, Role.RESULT)
    raw = session.declare_publisher(keys.markers("cam0"))
    try:
        node = start_node(procs, "marker_pose", "marker", input="detections", calib=str(calib))
        wait_live(session, keys, {"marker"}, [node])
        wait_until(out.matched, START_S, "the node to subscribe to the detections")
        T = next(T for _, child, T in scene.render(0).truth[camera.name] if child == "marker/3")
        corners = project_points(transform_points(T, grid_map("b", 1, 1, LENGTH, 0).markers[0].corners()),
                                 camera.K, camera.dist)

        def detections(seq: int, quad: np.ndarray) -> MarkerDetections:
            return MarkerDetections(header=Header(stamp_ns=1, frame_id="cam0", seq=seq), dictionary="DICT_4X4_50",
                                    ids=np.array([3], np.int32), corners=quad[None].astype(np.float32),
                                    quality=np.ones(1, np.float32), side_m=np.full(1, LENGTH, np.float32))

        out.put(detections(0, np.full((4, 2), 100.0)))  # four coincident corners
        out.put(detections(1, np.array([[0, 0], [10, 10], [20, 20], [30, 30]], float)))  # collinear
        raw.put(b"\x00garbage")
        out.put(detections(2, corners))
        got = collect(poses, lambda got: any(p.header.seq == 2 for p in got))
        assert [p.header.seq for p in got] == [2] and got[0].state is TrackingState.TRACKING
        rotation, translation = pose_error(matrix_from_transform(got[0].transform), T)
        assert np.degrees(rotation) < 1e-3 and translation < 1e-5
        stats = wait_until(lambda: states(session, keys).get("marker"), START_S, "the node's state")
        assert stats.skipped == {"degenerate_corners": 2, "decode_error": 1}, stats.skipped
        assert node.poll() is None
    finally:
        raw.undeclare()
        out.close()
        poses.close()


def test_the_bundled_two_node_board_pipeline_runs_under_up(bus, procs, session):
    poses = Inbox(session, bus.keys.pose("cam0/board"), Pose, Role.RESULT)
    try:
        up = procs.artrack("up", "pipelines/marker_board.toml", "--rig", bus.rig, name="up")
        got = collect(poses, lambda got: sum(p.state is TrackingState.TRACKING for p in got) >= 5, 2 * START_S)
        board = [p for p in got if p.state is TrackingState.TRACKING]
        assert all(p.header.frame_id == "cam0" and p.quality.inliers >= 8 for p in board)
        assert all(0.2 < np.linalg.norm(p.transform.translation) < 1.5 for p in board)
        assert up.poll() is None, up.describe()
    finally:
        poses.close()
