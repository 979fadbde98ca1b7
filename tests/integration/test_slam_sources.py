"""``artrack run slam`` on a recording and on a video file, by real processes over a real bus: the room scene
recorded (or written to a lossless video beside its calibration file) is tracked and scored against its
ground truth; a source path that does not exist, or a file that is no video, is refused in one line before any job
starts (how long that takes is the ``refusals`` benchmark's)."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from protocol.poses import Pose
from protocol.tracking_state import TrackingState
from services.calibration.camera_info import write_camera_info
from services.convert import matrix_from_transform
from services.geometry.evaluation import score_trajectory
from tests.integration.support import START_S
from tests.integration.test_marker_pipeline import recorded
from tests.slam_passes import NANOSECONDS, room_frames, room_scene

pytestmark = pytest.mark.integration

FRAMES = 60
FPS = 30
KEY = "pose/slam/cam0"
ATE_BAR_M = 0.05
"""Loose bar on the ATE after Sim(3) (metres of the room): tracked in process, the room scores 1-2 cm."""


def _slam(procs, *options: str) -> list[Pose]:
    """Run ``artrack run slam`` with ``options`` (recording to the last one) and return its poses."""
    job = procs.artrack("run", "slam", "--depth", str(FRAMES), "--mapping", "inline", *options, name="job")
    assert job.wait(8 * START_S) == 0, job.describe()
    messages = recorded(options[-1])
    prefix = next(key for key in messages if key.endswith("/cam0/image")).removesuffix("/cam0/image")
    poses: list[Pose] = messages[f"{prefix}/{KEY}"]
    assert [p.header.seq for p in poses] == list(range(FRAMES)), [p.header.seq for p in poses]  # none dropped
    states_seen = [p.state for p in poses]
    first = states_seen.index(TrackingState.TRACKING)
    assert first < FRAMES // 3 and states_seen.count(TrackingState.TRACKING) >= 0.9 * (FRAMES - first), states_seen
    return poses


def test_slam_tracks_a_recorded_session_and_scores_against_its_recorded_truth(procs, tmp_path):
    session, out = tmp_path / "room.mcap", tmp_path / "slam.mcap"
    capture = procs.artrack("run", "capture", "--source", "synthetic:room", "--frames", str(FRAMES), "--record",
                            str(session), name="capture")
    assert capture.wait(8 * START_S) == 0, capture.describe()
    poses = _slam(procs, "--source", f"recording:{session}", "--record", str(out))
    tracking = sum(p.state is TrackingState.TRACKING for p in poses)

    scored = procs.run("eval", str(out), str(out), "--est-key", KEY, "--gt-key", "cam0/truth", "--gt-child", "cam0",
                       "--align", "sim3", "--json")  # the truth is replayed with the frames, restamped alike
    assert scored.poll() == 0, scored.describe()
    figures = json.loads(scored.stdout)
    print(f"recording: {tracking} of {FRAMES} frames tracked, ATE {figures['ate_m']['rmse'] * 100:.2f} cm")
    assert figures["matched"] == tracking
    assert figures["ate_m"]["rmse"] <= ATE_BAR_M, figures["ate_m"]


def test_slam_tracks_a_video_file_with_a_calibration_file_scored_by_frame_index(procs, tmp_path):
    scene = room_scene()
    video, calib, out = tmp_path / "room.mkv", tmp_path / "cam0.yaml", tmp_path / "slam.mcap"
    camera = scene.cameras[0]
    write_camera_info(calib, camera)
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"FFV1"), FPS, (camera.width, camera.height),
                             isColor=False)  # FFV1 is lossless: the node sees the rendered frames
    truth = []
    for _, image, T_world_cam0 in room_frames(scene, range(FRAMES)):
        writer.write(image)
        truth.append(T_world_cam0)
    writer.release()

    poses = _slam(procs, "--source", f"video:{video}", "--calib", str(calib), "--stamps", "source",
                  "--record", str(out))
    tracking = [p for p in poses if p.state is TrackingState.TRACKING]
    stamps_ns = np.array([p.header.stamp_ns for p in tracking])
    indices = np.rint(stamps_ns * FPS / NANOSECONDS).astype(int)  # the container's times, to the millisecond
    assert np.all(np.abs(stamps_ns - indices * NANOSECONDS / FPS) <= 1e6), stamps_ns
    assert indices.tolist() == [p.header.seq for p in tracking]
    score = score_trajectory(np.array([matrix_from_transform(p.transform) for p in tracking]),
                             np.array(truth)[indices], "sim3")
    print(f"video: {len(tracking)} of {FRAMES} frames tracked, ATE {score.ate.stats.rmse * 100:.2f} cm")
    assert score.ate.stats.rmse <= ATE_BAR_M, score.ate.stats


@pytest.mark.parametrize(("source", "expected"), [
    ("video:/nope.mkv", "video:/nope.mkv: no such file"),
    ("recording:/nope.mcap", "recording:/nope.mcap: no such recording"),
    ("video:{garbage}", "video:{garbage}: OpenCV cannot read this file"),
], ids=["missing-video", "missing-recording", "garbage-video"])
def test_a_source_that_cannot_be_read_is_refused_in_one_line_before_starting(procs, tmp_path, source, expected):
    garbage = tmp_path / "garbage.mkv"
    garbage.write_bytes(b"not a video, " * 400)
    source, expected = source.format(garbage=garbage), expected.format(garbage=garbage)
    job = procs.run("run", "slam", "--source", source, "--depth", "5")
    assert job.poll() == 2, job.describe()
    lines = [line for line in job.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and expected in lines[0], job.stderr
