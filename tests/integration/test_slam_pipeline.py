"""``artrack run slam``: the room scene tracked by real processes over a real bus, recorded, exported, scored
against the recorded truth and viewed; bad frames counted while the node goes on."""

from __future__ import annotations

import json
import random

import numpy as np
import pytest

from protocol.message import Header
from protocol.poses import Pose
from protocol.sensors import CameraInfo, Image
from protocol.tracking_state import TrackingState
from services.bus.pubsub import Inbox, Publisher, Role
from services.calibration.camera_info import write_camera_info
from services.convert import camera_info, camera_model, matrix_from_transform
from services.geometry.camera import CameraModel
from services.geometry.evaluation import score_trajectory
from services.recorder.trajectories import read_kitti
from services.synthetic import make_scene
from tests.data import data_dir
from tests.integration.support import START_S, collect, start_node, states, wait_live, wait_until
from tests.integration.test_marker_pipeline import recorded
from tests.viewer_contents import RrdContents

pytestmark = pytest.mark.integration

FRAMES = 90
KEY = "pose/slam/cam0"


def test_slam_run_tracks_the_room_records_exports_scores_and_views(procs, tmp_path):
    out, view = tmp_path / "slam.mcap", tmp_path / "slam.rrd"
    job = procs.artrack("run", "slam", "--source", "synthetic:room", "--frames", str(FRAMES), "--depth", str(FRAMES),
                        "--map-every", "5", "--record", str(out), "--rerun", str(view), name="job")
    assert job.wait(8 * START_S) == 0, job.describe()
    messages = recorded(out)
    prefix = next(key for key in messages if key.endswith("/cam0/image")).removesuffix("/cam0/image")
    poses: list[Pose] = messages[f"{prefix}/{KEY}"]
    assert [p.header.seq for p in poses] == list(range(FRAMES))  # frames queue (--depth): a pose for every one
    assert all((p.header.frame_id, p.child_frame_id) == ("map", "cam0") for p in poses)
    states_seen = [p.state for p in poses]
    assert states_seen[0] is TrackingState.INITIALISING and poses[0].reason
    first = states_seen.index(TrackingState.TRACKING)
    tracking = [p for p in poses if p.state is TrackingState.TRACKING]
    assert first < FRAMES // 3 and len(tracking) >= 0.9 * (FRAMES - first), states_seen
    assert all(p.quality.inliers >= 30 and p.quality.reprojection_rms_px <= 3.0 for p in tracking)
    assert all(p.reason == "" for p in tracking)

    keyframes = messages[f"{prefix}/cam0/keyframes"]
    last = keyframes[-1]
    assert len(last.ids) >= 2 and np.all(np.diff(last.ids) > 0) and last.header.frame_id == "map"
    assert set(last.stamps_ns.tolist()) <= {p.header.stamp_ns for p in poses}
    assert all(not np.array_equal(a.poses, b.poses) or len(a.ids) != len(b.ids)
               for a, b in zip(keyframes, keyframes[1:], strict=False))  # sent only when they changed
    clouds = messages[f"{prefix}/cam0/map"]
    assert len(clouds[-1].points) >= 100 and len(np.unique(clouds[-1].ids)) == len(clouds[-1].ids)
    assert np.all(np.diff([c.header.seq for c in clouds[:-1]]) >= 5)  # at most every --map-every frames
    [final] = messages[f"{prefix}/cam0/trajectory"]  # one map, ended as the node stopped
    assert (final.header.frame_id, final.child_frame_id) == ("map", "cam0")
    assert final.seqs.tolist() == [p.header.seq for p in tracking]
    assert final.stamps_ns.tolist() == [p.header.stamp_ns for p in tracking]
    timings = messages[f"{prefix}/cam0/timings"]
    assert len(timings) == FRAMES and all("total" in t.stages_ms for t in timings)
    stats = messages[f"{prefix}/node/slam-cam0/stats"][-1]
    assert stats.skipped == {} and stats.decode_errors == 0 and stats.processed == FRAMES

    tum = tmp_path / "slam.tum"
    export = procs.run("export", str(out), "--key", KEY, "--format", "tum", "--output", str(tum))
    assert export.poll() == 0, export.describe()
    rows = np.array([[float(v) for v in line.split()] for line in tum.read_text().splitlines() if line])
    assert rows.shape == (len(tracking), 8)
    assert np.allclose(rows[:, 1:4], [p.transform.translation for p in tracking])

    scored = procs.run("eval", str(tum), str(out), "--gt-key", "cam0/truth", "--gt-child", "cam0", "--align", "sim3",
                       "--json")
    assert scored.poll() == 0, scored.describe()
    figures = json.loads(scored.stdout)
    assert figures["matched"] == len(tracking)
    assert figures["ate_m"]["rmse"] <= 0.05, figures["ate_m"]  # metres of the room, after a similarity alignment
    assert figures["rpe"]["rotation_deg"]["median"] <= 0.5, figures["rpe"]
    final_scored = procs.run("eval", str(out), str(out), "--est-key", "cam0/trajectory", "--gt-key", "cam0/truth",
                             "--gt-child", "cam0", "--align", "sim3", "--json")
    assert final_scored.poll() == 0, final_scored.describe()
    final_figures = json.loads(final_scored.stdout)
    assert final_figures["matched"] == len(tracking) and final_figures["ate_m"]["rmse"] <= 0.05, final_figures

    viewed = RrdContents(view)
    assert len(viewed.rows("world/map/pose/cam0", "Transform3D:translation")) == len(tracking)
    assert viewed.rows("world/map/trajectory/pose/cam0", "LineStrips3D:strips")
    drawn = viewed.rows("world/map/keyframes/cam0", "Arrows3D:origins")[-1]
    assert len(drawn.values) == 3 * len(last.ids)  # three axes a keyframe
    points = viewed.rows("world/map/points", "Points3D:positions")[-1]  # the final map may come as the viewer stops
    assert len(points.values) == len(next(c for c in clouds if c.header.seq == points.times["seq"]).points)
    assert viewed.rows("stats/stage_ms/cam0/total", "Scalars:scalars")


def test_slam_on_the_real_tum_folder_with_a_calibration_file_scores_against_its_ground_truth(procs, tmp_path):
    folder = data_dir("tum_rgbd_fr3_long_office_household_1hz")
    calib, out = tmp_path / "fr3.yaml", tmp_path / "tum.mcap"
    write_camera_info(calib, CameraModel("cam0", 640, 480, np.array([[535.4, 0, 320.1], [0, 539.2, 247.6], [0, 0, 1]]),
                                         np.zeros(5), np.eye(4)))  # TUM's freiburg3 colour camera
    job = procs.artrack("run", "slam", "--source", f"images:{folder / 'rgb'}", "--calib", str(calib), "--stamps",
                        "source", "--fps", "5", "--depth", "20", "--mapping", "inline", "--record", str(out),
                        name="job")  # sent at 5 fps, stamped with the sequence's own times
    assert job.wait(8 * START_S) == 0, job.describe()
    scored = procs.run("eval", str(out), str(folder / "groundtruth.txt"), "--est-key", KEY, "--align", "sim3", "--json")
    assert scored.poll() == 0, scored.describe()
    figures = json.loads(scored.stdout)
    assert figures["matched"] >= 18 and figures["ate_m"]["rmse"] <= 0.04, figures  # 20 frames about 1 s apart


def test_slam_on_the_real_kitti_folder_is_calibrated_by_its_calib_file(procs, tmp_path):
    folder = data_dir("vo_kitti_odometry_seq06_frames000-050")
    out = tmp_path / "kitti.mcap"
    job = procs.artrack("run", "slam", "--source", f"images:{folder / 'image_0'}", "--fps", "10", "--frames", "20",
                        "--depth", "20", "--mapping", "inline", "--record", str(out), name="job")
    assert job.wait(8 * START_S) == 0, job.describe()
    messages = recorded(out)
    prefix = next(key for key in messages if key.endswith("/cam0/image")).removesuffix("/cam0/image")
    camera = camera_model(messages[f"{prefix}/cam0/camera_info"][0])
    assert np.allclose(camera.K, [[707.0912, 0, 601.8873], [0, 707.0912, 183.1104], [0, 0, 1]])  # calib.txt's P0
    tracking = [p for p in messages[f"{prefix}/{KEY}"] if p.state is TrackingState.TRACKING]
    assert len(tracking) >= 15, [p.state for p in messages[f"{prefix}/{KEY}"]]
    truth = read_kitti(folder / "poses.txt").poses[[p.header.seq for p in tracking]]  # KITTI poses are by frame
    score = score_trajectory(np.array([matrix_from_transform(p.transform) for p in tracking]), truth, "sim3")
    assert score.ate.stats.rmse <= 0.2, score.ate.stats  # metres, over the 20 m the car drives
    final = procs.run("eval", str(out), str(folder / "poses.txt"), "--est-key", "cam0/trajectory", "--align", "sim3",
                      "--json")  # the final trajectory, matched to poses.txt's rows by frame number
    assert final.poll() == 0, final.describe()
    figures = json.loads(final.stdout)
    assert figures["matched"] == len(tracking) and figures["ate_m"]["rmse"] <= 0.2, figures


def test_garbage_and_unusable_frames_are_counted_while_the_node_goes_on(bus, procs, session):
    scene = make_scene("room")
    keys = bus.keys
    poses = Inbox(session, keys.slam_pose("cam0"), Pose, Role.RESULT)
    frames = Publisher(session, keys.image("cam0"), Image, Role.RESULT)
    infos = Publisher(session, keys.camera_info("cam0"), CameraInfo, Role.RESULT)
    raw = session.declare_publisher(keys.image("cam0"))
    seen: dict[int, Pose] = {}

    def send(seq: int, data: np.ndarray) -> Pose:
        frames.put(Image(header=Header(stamp_ns=1_000 + seq, frame_id="cam0", seq=seq), encoding="mono8", data=data))
        got = collect(poses, lambda got: any(p.header.seq == seq for p in got))
        seen.update((p.header.seq, p) for p in got)
        return seen[seq]

    def received(key: str) -> int:
        stats = states(session, keys).get("slam")
        return 0 if stats is None else sum(s.messages for s in stats.streams if s.key == key and s.direction == "in")

    def decode_errors() -> int:
        stats = states(session, keys).get("slam")
        return 0 if stats is None else stats.decode_errors

    try:
        node = start_node(procs, "slam", "slam", depth=10)
        wait_live(session, keys, {"slam"}, [node])
        wait_until(lambda: frames.matched() and infos.matched() and raw.matching_status.matching, START_S,
                   "the node to subscribe")
        room = [scene.render(i).images["cam0"] for i in range(2)]
        assert (send(0, room[0]).state, seen[0].reason) == (TrackingState.LOST, "no_calibration")
        infos.put(camera_info(Header(stamp_ns=1_000, frame_id="cam0"), scene.cameras[0]))
        wait_until(lambda: received(keys.camera_info("cam0")) == 1, START_S, "the CameraInfo to arrive")
        assert send(1, room[0]).state is TrackingState.INITIALISING
        raw.put(random.Random(3).randbytes(4096))
        wait_until(lambda: decode_errors() == 1, START_S, "the garbage to be counted")
        assert (send(2, np.zeros((4, 4), np.uint8)).state, seen[2].reason) == (TrackingState.LOST, "unusable_frame")
        after = send(3, room[1])
        assert after.state is TrackingState.INITIALISING and after.reason not in ("unusable_frame", "no_calibration")
        stats = wait_until(lambda: (s := states(session, keys).get("slam")) and s.processed == 4 and s, START_S,
                           "the node to count 4 frames")
        assert node.poll() is None, node.describe()
        assert stats.skipped == {"no_calibration": 1, "decode_error": 1, "unusable_frame": 1}, stats.skipped
    finally:
        raw.undeclare()
        infos.close()
        frames.close()
        poses.close()
