"""``artrack run slam --anchor-marker``: the room with its marker tracked over a real bus, the slam node
posing the marker itself and publishing the camera in the marker's frame, in metres."""

from __future__ import annotations

import numpy as np
import pytest

from protocol.poses import Pose, TrackingState
from services.capture.scenes import make_scene
from services.capture.scenes.room import RoomScene
from services.convert import matrix_from_transform
from services.geometry.evaluation import absolute_trajectory_error
from services.geometry.se3 import invert
from tests.integration.support import START_S
from tests.integration.test_marker_pipeline import recorded

pytestmark = pytest.mark.integration

FRAMES = 150
"""The marker is first seen whole at frame 45; the anchor needs 0.3 m of baseline after that."""
KEY = "pose/slam/cam0/anchored"


def test_slam_run_with_an_anchor_marker_gives_metric_poses_in_the_marker_frame(procs, tmp_path):
    out = tmp_path / "anchored.mcap"
    job = procs.artrack("run", "slam", "--source", "synthetic:room", "--scene-option", "marker=true",
                        "--anchor-marker", "0", "--frames", str(FRAMES), "--depth", str(FRAMES),
                        "--no-mapping-thread", "--record", str(out), name="job")
    assert job.wait(8 * START_S) == 0, job.describe()
    messages = recorded(out)
    prefix = next(key for key in messages if key.endswith("/cam0/image")).removesuffix("/cam0/image")
    anchored: list[Pose] = messages[f"{prefix}/{KEY}"]
    assert len(anchored) == FRAMES and all(p.header.frame_id == "marker/0" for p in anchored)
    tracking = [p for p in anchored if p.state is TrackingState.TRACKING]
    waiting = [p.reason for p in anchored[:45] if p.state is TrackingState.INITIALIZING]
    assert "too_few_frames" in waiting and len(tracking) >= 40, [(p.state, p.reason) for p in anchored]
    scene = make_scene("room", marker=True)
    assert isinstance(scene, RoomScene) and scene.T_world_marker is not None
    truth = np.array([invert(scene.T_world_marker) @ scene.camera_pose(p.header.seq) for p in tracking])
    estimate = np.array([matrix_from_transform(p.transform) for p in tracking])
    error = absolute_trajectory_error(estimate, truth, align="none")
    assert error.stats.rmse <= 0.05, error.stats  # metres in the marker's frame, no alignment
