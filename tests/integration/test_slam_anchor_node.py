"""``artrack run slam --anchor-marker``: the room with its marker tracked over a real bus, the slam node
posing the marker itself and publishing the camera in the marker's frame, in metres."""

from __future__ import annotations

import numpy as np
import pytest

from protocol.poses import Pose
from protocol.tracking_state import TrackingState
from services.convert import matrix_from_transform
from services.geometry.evaluation import absolute_trajectory_error
from services.geometry.se3 import invert
from services.synthetic import make_scene
from services.synthetic.room import RoomScene
from tests.integration.support import START_S
from tests.integration.test_marker_pipeline import recorded

pytestmark = pytest.mark.integration

FRAMES = 150
"""The marker is seen whole in frames 45-121; the anchor needs 0.3 m of baseline after the first, and the last
frames look away from it."""
KEY = "pose/slam/cam0/anchored"
SEEN = range(45, 122)
"""Frames that see the marker whole."""


def test_slam_run_with_an_anchor_marker_gives_metric_poses_in_the_marker_frame(procs, tmp_path):
    """Mapping inline and the scene's own clock for stamps (keyframes are spaced in time), so the run does
    not depend on how busy the machine is."""
    out = tmp_path / "anchored.mcap"
    job = procs.artrack("run", "slam", "--source", "synthetic:room", "--scene-option", "marker=true",
                        "--anchor-marker", "0", "--frames", str(FRAMES), "--depth", str(FRAMES),
                        "--mapping", "inline", "--stamps", "source", "--record", str(out), name="job")
    assert job.wait(8 * START_S) == 0, job.describe()
    messages = recorded(out)
    prefix = next(key for key in messages if key.endswith("/cam0/image")).removesuffix("/cam0/image")
    anchored: list[Pose] = messages[f"{prefix}/{KEY}"]
    assert len(anchored) == FRAMES and all(p.header.frame_id == "marker/0" for p in anchored)
    tracking = [p for p in anchored if p.state is TrackingState.TRACKING]
    waiting = [p.reason for p in anchored[:45] if p.state is TrackingState.INITIALISING]
    assert "too_few_frames" in waiting and len(tracking) >= 40, [(p.state, p.reason) for p in anchored]
    scene = make_scene("room", marker=True)
    assert isinstance(scene, RoomScene) and scene.T_world_marker is not None
    truth = np.array([invert(scene.T_world_marker) @ scene.camera_pose(p.header.seq) for p in tracking])
    estimate = np.array([matrix_from_transform(p.transform) for p in tracking])
    in_view = np.array([p.header.seq in SEEN for p in tracking])
    error = absolute_trajectory_error(estimate, truth, align="none")  # metres in the marker's frame, no alignment
    seen = absolute_trajectory_error(estimate[in_view], truth[in_view], align="none")
    origins = [invert(a)[:3, 3] - invert(b)[:3, 3] for a, b in zip(estimate, truth, strict=True)]
    in_camera = float(np.sqrt(np.mean(np.sum(np.square(origins), axis=1))))
    print(f"\nanchored from frame {tracking[0].header.seq}, {len(tracking)} frames: position RMSE "
          f"{seen.stats.rmse * 1e3:.1f} mm in view of the marker, {error.stats.rmse * 1e3:.1f} mm over all; "
          f"marker origin in the camera {in_camera * 1e3:.1f} mm RMS")
    assert in_view.sum() >= 30 and seen.stats.rmse <= 0.03, seen.stats  # while the marker is in view
    assert error.stats.rmse <= 0.1, error.stats  # and after, as the map drifts away from it
    assert in_camera <= 0.02, in_camera  # where the marker's origin lands in the camera frame
