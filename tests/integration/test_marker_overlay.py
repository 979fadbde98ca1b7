"""The marker node's AR overlay in real processes: drawn on the frames, on the bus, and in the Rerun recording."""

from __future__ import annotations

import json

import numpy as np
import pytest

from protocol import CameraInfo, Image, Pose, TrackingState
from services.bus.pubsub import Inbox, Role
from services.convert import camera_model, matrix_from_transform
from services.estimation.overlay import cube_edges, to_bgr8
from services.geometry.camera import project_points
from services.geometry.se3 import transform_points
from tests.viewer_contents import RrdContents

from .support import START_S

pytestmark = pytest.mark.integration

FRAMES, FPS, MARKER_LENGTH = 10, 20, 0.05
OVERLAY_ENTITY = "world/cam0/overlay/image"


def drain(inbox: Inbox) -> list:
    found = []
    while (received := inbox.take()) is not None:
        found.append(received.message)
    return found


def test_run_marker_with_overlay_publishes_drawn_frames_and_logs_them_to_rerun(bus, procs, session, tmp_path):
    keys, out = bus.keys, tmp_path / "job.rrd"
    inboxes = {
        "overlay": Inbox(session, keys.overlay("cam0"), Image, Role.FRAME, depth=4 * FRAMES),
        "image": Inbox(session, keys.image("cam0"), Image, Role.FRAME, depth=4 * FRAMES),
        "info": Inbox(session, keys.camera_info("cam0"), CameraInfo, Role.RESULT),
        "pose": Inbox(session, keys.poses(), Pose, Role.RESULT),
    }
    try:
        job = procs.artrack("run", "marker", "--source", "synthetic:markers", "--frames", str(FRAMES),
                            "--fps", str(FPS), "--marker-length", str(MARKER_LENGTH), "--overlay",
                            "--rerun", str(out), name="job")
        assert job.wait(3 * START_S) == 0, job.describe()
        got = {name: drain(inbox) for name, inbox in inboxes.items()}
    finally:
        for inbox in inboxes.values():
            inbox.close()

    frames = {image.header.seq: image for image in got["image"]}
    overlays = {image.header.seq: image for image in got["overlay"]}
    assert len(frames) == FRAMES and len(overlays) >= FRAMES // 2, (sorted(frames), sorted(overlays))
    camera = camera_model(got["info"][0])
    tracked: dict[int, list[np.ndarray]] = {}
    for pose in got["pose"]:
        if pose.state is TrackingState.TRACKING and pose.child_frame_id.startswith("marker/"):
            tracked.setdefault(pose.header.seq, []).append(matrix_from_transform(pose.transform))

    corners_checked = 0
    for seq, overlay in overlays.items():
        frame = frames[seq]
        assert overlay.encoding == "bgr8" and overlay.data.shape == (*frame.data.shape[:2], 3)
        assert overlay.header.frame_id == "cam0/overlay"
        assert (overlay.header.stamp_ns, overlay.header.seq) == (frame.header.stamp_ns, frame.header.seq)
        drawn = np.any(overlay.data != to_bgr8(frame.data), axis=2)
        if seq not in tracked:
            continue
        for T in tracked[seq]:  # each tracked marker's cube corners are drawn over the frame
            corners = project_points(transform_points(T, cube_edges(MARKER_LENGTH)[:, 0]), camera.K, camera.dist)
            inside = (corners[:, 0] >= 0) & (corners[:, 0] <= camera.width - 1) & (corners[:, 1] >= 0) \
                & (corners[:, 1] <= camera.height - 1)
            for u, v in np.round(corners[inside]).astype(int):
                assert drawn[v, u], f"frame {seq}: no overlay at a cube corner ({u}, {v})"
                corners_checked += 1
    assert corners_checked >= 4 * FRAMES // 2, corners_checked

    contents = RrdContents(out)
    logged = contents.rows(OVERLAY_ENTITY, "Image:buffer")
    assert 3 <= len(logged) <= FRAMES, len(logged)  # 0.5 s of frames at the viewer's 10 Hz image limit
    for row in logged:
        if row.times["seq"] in overlays:
            np.testing.assert_array_equal(row.numbers(), overlays[row.times["seq"]].data.ravel())
    assert not contents.rows(OVERLAY_ENTITY, "Pinhole:image_from_camera")  # 2D only: not drawn in the 3D view
    assert contents.rows("world/cam0/image", "Image:buffer")  # the camera's own frames are still there
    views = contents.views()
    assert ("2D", OVERLAY_ENTITY) in views and ("2D", "world/cam0/image") in views, views


def test_overlay_is_refused_without_frames(procs):
    node = procs.run("node", "marker_pose", "--name", "marker", "--params",
                     json.dumps({"input": "detections", "overlay": True}))
    assert node.poll() == 2, node.describe()
    assert "overlay draws on the camera's frames: it needs input 'images'" in node.stderr


def test_run_refuses_overlay_for_a_pipeline_that_draws_nothing(procs):
    job = procs.run("run", "echo", "--source", "synthetic:pattern", "--overlay")
    assert job.poll() == 2, job.describe()
    assert "unrecognized arguments: --overlay" in job.stderr
