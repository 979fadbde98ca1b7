"""``SlamSystem.trajectory``: every tracked frame's pose through its reference keyframe's current pose."""

import numpy as np
import pytest

from protocol.tracking_state import TrackingState
from services.geometry.rotation import matrix_from_rotvec
from services.geometry.se3 import invert, make_transform
from services.slam.system import SlamSystem
from services.synthetic import make_scene

pytestmark = pytest.mark.slow


def test_trajectory_follows_the_keyframes():
    scene = make_scene("room")
    system = SlamSystem(scene.cameras[0], mapping="inline")
    online: dict[int, np.ndarray] = {}
    keyframe_stamps = set()
    for index in range(90):
        frame = scene.render(index)
        stamp = round(frame.time_s * 1e9)
        result = system.process(stamp, frame.images["cam0"])
        if result.state is TrackingState.TRACKING:
            assert result.T_world_camera is not None
            online[stamp] = result.T_world_camera
        if result.keyframe_id is not None:
            keyframe_stamps.add(stamp)
    system.close()
    trajectory = system.trajectory()
    assert [stamp for stamp, _ in trajectory] == list(online) and len(online) > 60
    final = dict(trajectory)
    # a frame that became a keyframe is that keyframe's current pose (bundle adjusted since)
    keyframes = {stamp: T for _, stamp, T in system.keyframe_poses()}
    for stamp in keyframe_stamps:
        np.testing.assert_allclose(final[stamp], keyframes[stamp], atol=1e-12)
    # the local bundle adjustment moved keyframes after their frames were tracked: the final poses
    # differ from the online ones, by little (the map's median depth is 1)
    moved = [float(np.linalg.norm(final[s][:3, 3] - online[s][:3, 3])) for s in online]
    assert 1e-6 < max(moved) < 0.05, max(moved)
    # the whole map moved by one rigid motion G (world' = G world): every frame moves with it
    G = make_transform(matrix_from_rotvec(np.array([0.1, -0.2, 0.3])), np.array([0.5, -1.0, 2.0]))
    with system.map.lock:
        for keyframe in list(system.map.keyframes.values()):
            system.map.set_pose(keyframe.id, keyframe.T_camera_world @ invert(G))
    for stamp, T in system.trajectory():
        np.testing.assert_allclose(T, G @ final[stamp], atol=1e-9)
