"""A capture node's static transforms: published once, answered to late joiners, a FrameGraph for client apps."""

from __future__ import annotations

import numpy as np
import pytest

from protocol import RIG_FRAME, StaticTransforms
from services.bus.pubsub import Inbox, Role
from services.client import BusSettings, Client
from services.convert import frame_graph
from services.geometry.rotation import rotation_angle
from services.geometry.se3 import invert
from services.synthetic.ir_rig import IrRigOptions, IrRigScene
from tests.integration.support import START_S, collect, start_node, wait_live

pytestmark = pytest.mark.integration

SCENE = {"camera_count": 2, "width": 320, "height": 240, "baseline": 0.25}


def test_a_client_joining_late_gets_the_rig_s_frames_as_the_scene_placed_them(bus, procs, session):
    keys = bus.keys
    published = Inbox(session, keys.static_transforms("bar"), StaticTransforms, Role.RESULT)
    images = [Inbox(session, keys.image(name), None, Role.FRAME) for name in ("cam0", "cam1")]
    try:
        capture = start_node(procs, "capture", "bar", source="synthetic:ir_rig", scene=SCENE, fps=5, loop=True,
                             wait_for_subscriber=True)
        wait_live(session, keys, {"bar"}, (capture,))
        live = collect(published, 1)[0]
        with Client(BusSettings(connect=(bus.endpoint,), rig=bus.rig), app="frames") as ar:
            graph = ar.frames(timeout_s=START_S)
    finally:
        for inbox in [published, *images]:
            inbox.close()

    cameras = IrRigScene(IrRigOptions(**SCENE)).cameras
    truth = invert(cameras[0].T_rig_camera) @ cameras[1].T_rig_camera
    T_cam0_cam1 = graph.transform("cam0", "cam1")
    assert sorted(graph.frames()) == ["cam0", "cam1", RIG_FRAME]
    assert rotation_angle(T_cam0_cam1[:3, :3], truth[:3, :3]) < 1e-9
    assert np.allclose(T_cam0_cam1[:3, 3], truth[:3, 3], atol=1e-12)
    assert np.isclose(np.linalg.norm(T_cam0_cam1[:3, 3]), 0.25, atol=1e-12)  # the bar's baseline
    assert np.allclose(graph.transform(RIG_FRAME, "cam1"), cameras[1].T_rig_camera, atol=1e-12)

    assert live.header.frame_id == RIG_FRAME
    assert [(e.parent_frame, e.child_frame) for e in live.transforms] == [(RIG_FRAME, "cam0"), (RIG_FRAME, "cam1")]
    assert np.allclose(frame_graph([live]).transform("cam0", "cam1"), T_cam0_cam1, atol=1e-15)


def test_a_rig_nobody_describes_gives_an_empty_graph(bus):
    with Client(BusSettings(connect=(bus.endpoint,), rig=bus.rig), app="frames") as ar:
        assert ar.frames(timeout_s=0.5).frames() == []
