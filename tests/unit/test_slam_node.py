"""The slam node without a bus: map points cut to a count, a frame's result as a Pose, and the keyframe
decisions of a lossless run waiting for the mapper."""

from __future__ import annotations

import logging
import math
from types import SimpleNamespace

import numpy as np
import pytest

from protocol.keys import Keys
from protocol.message import Header
from protocol.tracking_state import TrackingState
from services.convert import matrix_from_transform
from services.geometry.camera import CameraModel, intrinsics
from services.geometry.rotation import matrix_from_rotvec
from services.geometry.se3 import make_transform
from services.runtime.flow import FlowPlan
from services.slam.node import Params, _CameraSlam, as_pose, decimated
from services.slam.system import FrameResult

HEADER = Header(stamp_ns=5, frame_id="map", seq=2)


def test_a_map_with_more_points_than_asked_is_cut_evenly_over_its_ids():
    ids = np.arange(100, 1100, dtype=np.int64)
    points = np.c_[ids, ids, ids].astype(np.float64)
    kept_ids, kept = decimated(ids, points, 10)
    assert len(kept_ids) == 10 and kept_ids[0] == 100 and kept_ids[-1] == 1099
    assert np.all(np.diff(kept_ids) >= 110) and np.array_equal(kept[:, 0], kept_ids)
    same_ids, same = decimated(ids[:5], points[:5], 10)  # fewer than asked: all of them
    assert np.array_equal(same_ids, ids[:5]) and np.array_equal(same, points[:5])


def test_a_tracked_frame_becomes_its_pose_and_an_initialising_one_an_identity_with_its_reason():
    T = make_transform(matrix_from_rotvec([0.1, -0.2, 0.3]), [1.0, 2.0, 3.0])
    tracked = as_pose(HEADER, "cam0", FrameResult(TrackingState.TRACKING, "", T, 120, 0.8, None, {"total": 9.0}))
    assert (tracked.state, tracked.reason, tracked.child_frame_id) == (TrackingState.TRACKING, "", "cam0")
    assert np.allclose(matrix_from_transform(tracked.transform), T)
    assert (tracked.quality.inliers, tracked.quality.reprojection_rms_px) == (120, 0.8)
    waiting = as_pose(HEADER, "cam0",
                      FrameResult(TrackingState.INITIALISING, "low_parallax", None, 0, math.nan, None, {}))
    assert (waiting.state, waiting.reason) == (TrackingState.INITIALISING, "low_parallax")
    assert np.allclose(matrix_from_transform(waiting.transform), np.eye(4))
    assert waiting.quality.reprojection_rms_px is None and waiting.header == HEADER
    lost = as_pose(HEADER, "cam0", FrameResult(TrackingState.LOST, "too_few_matches", None, 0, math.nan, None, {}))
    assert lost.state is TrackingState.LOST


@pytest.mark.parametrize("lossless", [True, False])
def test_the_keyframe_decisions_wait_for_mapping_in_a_lossless_run_only(lossless):
    node = SimpleNamespace(keys=Keys(), flow=FlowPlan(lossless=lossless), publisher=lambda *_: None,
                           log=logging.getLogger(__name__))
    camera = CameraModel("cam0", 640, 480, intrinsics(640, 480, 60.0), np.zeros(5), np.eye(4))
    slam = _CameraSlam(node, Params(mapping="thread"))
    try:
        assert slam.system_for(camera, 0).wait_for_mapping is lossless
    finally:
        slam.close()
