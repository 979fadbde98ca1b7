"""``artrack run features``: image targets tracked by real processes, recorded, scored against the recorded truth,
exported, viewed and replayed; bad frames counted while the node goes on."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from protocol.message import Header
from protocol.poses import Pose
from protocol.sensors import CameraInfo, Image
from protocol.tracking_state import TrackingState
from services.bus.pubsub import Inbox, Publisher, Role
from services.convert import camera_info
from services.launcher.fixtures import write_fixtures
from services.synthetic import make_scene
from tests.integration.support import START_S, collect, start_node, states, wait_live, wait_until
from tests.integration.test_marker_pipeline import errors, recorded, truth_by_frame
from tests.viewer_contents import RrdContents

pytestmark = pytest.mark.integration

FRAMES = 30
KEY = "pose/cam0/target/planar_target"


def scored(path) -> tuple[list[Pose], np.ndarray, int]:
    """The recording's target poses, (rotation deg, translation % of distance) of each posed one against the
    recorded truth of its frame, and the frames the node dropped while busy (latest-wins)."""
    messages = recorded(path)
    prefix = next(key for key in messages if key.endswith("/cam0/image")).removesuffix("/cam0/image")
    poses = messages[f"{prefix}/{KEY}"]
    truth = truth_by_frame(messages[f"{prefix}/cam0/truth"])
    posed = [p for p in poses if p.state in (TrackingState.RECOGNISED, TrackingState.TRACKING)]
    dropped = messages[f"{prefix}/node/features-cam0/stats"][-1].dropped
    return poses, errors(posed, truth, lambda pose: "target"), dropped


def test_features_run_tracks_the_scenes_target_records_exports_views_and_replays(procs, tmp_path):
    out, view = tmp_path / "features.mcap", tmp_path / "features.rrd"
    job = procs.artrack("run", "features", "--source", "synthetic:planar_target", "--frames", str(FRAMES),
                        "--overlay", "--record", str(out), "--rerun", str(view), name="job")
    assert job.wait(4 * START_S) == 0, job.describe()
    assert "using --target planar_target, as synthetic:planar_target renders it" in job.stderr
    poses, table, dropped = scored(out)
    states_seen = [p.state for p in poses]
    assert states_seen[0] is TrackingState.RECOGNISED and set(states_seen[1:]) == {TrackingState.TRACKING}
    assert len(poses) + dropped == FRAMES and len(table) == len(poses) >= FRAMES / 2, (len(poses), dropped)
    assert np.median(table[:, 0]) <= 0.2 and np.median(table[:, 1]) <= 0.2, np.median(table, axis=0)
    assert all(p.quality.inliers >= 15 and p.quality.reprojection_rms_px <= 1.5 for p in poses)  # recognition's gates
    assert all(np.all(np.diag(np.reshape(p.covariance, (6, 6))) > 0) for p in poses)

    export = procs.run("export", str(out), "--key", "pose/cam0/target/*", "--format", "tum", "--out", str(tmp_path))
    assert export.poll() == 0, export.describe()
    rows = [line.split() for line in (tmp_path / f"{KEY}.tum").read_text().splitlines() if line]
    assert len(rows) == len(poses) and all(len(row) == 8 for row in rows)
    assert np.allclose([[float(v) for v in row[1:4]] for row in rows], [p.transform.translation for p in poses])

    viewed = RrdContents(view)
    assert len(viewed.rows("world/cam0/pose/target/planar_target", "Transform3D:translation")) == len(poses)
    assert "world/cam0/trajectory/pose/target/planar_target" in viewed.entities
    assert viewed.rows("world/cam0/overlay/image", "Image:buffer")

    again = tmp_path / "again.mcap"
    replay = procs.artrack("run", "features", "--source", f"recording:{out}", "--target", "synthetic:planar_target",
                           "--record", str(again), name="replay")
    assert replay.wait(4 * START_S) == 0, replay.describe()
    replayed, table, dropped = scored(again)
    assert len(replayed) + dropped == FRAMES and len(table) == len(replayed) >= FRAMES / 2, (len(replayed), dropped)
    assert replayed[0].state is TrackingState.RECOGNISED
    assert np.median(table[:, 0]) <= 0.2 and np.median(table[:, 1]) <= 0.2, np.median(table, axis=0)


def test_a_target_not_in_the_library_is_refused_before_anything_starts(procs, tmp_path):
    job = procs.run("run", "features", "--source", "synthetic:planar_target", "--frames", "3", "--target", "poster",
                    "--targets", str(tmp_path / "library"))
    assert job.poll() == 2, job.describe()
    lines = [line for line in job.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and f"no target 'poster' in {tmp_path / 'library'}" in lines[0], job.stderr
    assert "started" not in job.stderr


def test_every_encoding_is_recognised_and_a_featureless_frame_is_lost_counted_while_the_node_goes_on(
        bus, procs, session, tmp_path):
    scene = make_scene("planar_target")
    library = write_fixtures(tmp_path, scene.fixtures(), ("target",)).targets
    camera = scene.cameras[0]
    keys = bus.keys
    poses = Inbox(session, keys.pose("cam0/target/planar_target"), Pose, Role.RESULT)
    frames = Publisher(session, keys.image("cam0"), Image, Role.RESULT)
    infos = Publisher(session, keys.camera_info("cam0"), CameraInfo, Role.RESULT)
    try:
        node = start_node(procs, "features", "features", target=["planar_target"], targets=str(library), depth=10)
        wait_live(session, keys, {"features"}, [node])
        wait_until(lambda: frames.matched() and infos.matched(), START_S, "the node to subscribe")
        infos.put(camera_info(Header(stamp_ns=1_000, frame_id="cam0"), camera))
        frame, grey = scene.render(0).images["cam0"], np.full((480, 640), 128, np.uint8)
        sent = [(frame, "mono8"), (grey, "mono8"), (cv2.cvtColor(frame, cv2.COLOR_GRAY2BGR), "bgr8"),
                (grey, "mono8"), (frame.astype(np.uint16) * 257, "mono16"), (np.zeros((4, 4), np.uint8), "mono8"),
                (frame, "mono8")]  # grey: no texture; 4x4: too small to hold a feature
        seen: dict[int, Pose] = {}
        for seq, (data, encoding) in enumerate(sent):  # a lost target is recognised afresh in the next frame
            frames.put(Image(header=Header(stamp_ns=2_000 + seq, frame_id="cam0", seq=seq), encoding=encoding,
                             data=data))
            got = collect(poses, lambda got, seq=seq: any(p.header.seq == seq for p in got))
            seen.update((p.header.seq, p) for p in got)
        recognised, no_features = (TrackingState.RECOGNISED, ""), (TrackingState.LOST, "no_features")
        assert [(seen[i].state, seen[i].reason) for i in range(len(sent))] == [
            recognised, no_features, recognised, no_features, recognised, no_features, recognised], seen
        assert all(seen[i].quality.inliers >= 15 for i in (0, 2, 4, 6))
        stats = wait_until(lambda: states(session, keys).get("features"), START_S, "the node's state")
        assert node.poll() is None and stats.processed == len(sent), stats
        assert stats.skipped == {"no_features": 3}, stats.skipped
    finally:
        infos.close()
        frames.close()
        poses.close()
