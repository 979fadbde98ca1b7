"""StaticTransforms: what the message accepts, and its round trip to and from a FrameGraph over the wire."""

from __future__ import annotations

import numpy as np
import pytest
from pydantic import ValidationError

from protocol import RIG_FRAME, FrameTransform, Header, StaticTransforms, Transform, decode, encode
from services.convert import frame_graph, rig_static_transforms, static_transforms
from services.geometry.frames import FrameGraph, InconsistentCycleError
from services.geometry.rotation import matrix_from_rotvec
from services.geometry.se3 import invert, make_transform
from services.synthetic.ir_rig import IrRigOptions, IrRigScene

HEADER = Header(stamp_ns=1_700_000_000_000_000_000, frame_id=RIG_FRAME)


def edge(parent: str, child: str, x: float = 0.0) -> FrameTransform:
    return FrameTransform(parent_frame=parent, child_frame=child, transform=Transform(translation=(x, 0.0, 0.0)))


@pytest.mark.parametrize(("edges", "says"), [
    ([edge("rig", "cam0"), edge("rig", "cam0", 1.0)], "'rig' and 'cam0' are joined more than once"),
    ([edge("rig", "cam0"), edge("cam0", "rig")], "'cam0' and 'rig' are joined more than once"),
    ([edge("cam0", "cam0")], "'cam0' <- 'cam0' needs two named frames"),
    ([edge("", "cam0")], "'' <- 'cam0' needs two named frames"),
])
def test_a_pair_of_frames_is_joined_once_by_two_named_frames(edges: list[FrameTransform], says: str):
    with pytest.raises(ValidationError, match=says):
        StaticTransforms(header=HEADER, transforms=tuple(edges))


def test_a_graph_travels_through_the_wire_and_comes_back_the_same():
    rng = np.random.default_rng(11)
    graph = FrameGraph()
    for parent, child in (("world", "rig"), ("rig", "cam0"), ("rig", "cam1"), ("cam1", "marker")):
        graph.add(parent, child, make_transform(matrix_from_rotvec(rng.normal(0.0, 1.0, 3)), rng.uniform(-2, 2, 3)))
    message = decode(encode(static_transforms(HEADER, graph)))
    assert isinstance(message, StaticTransforms) and message.header == HEADER
    back = frame_graph([message])
    assert back.frames() == graph.frames()
    for (parent, child, T), (parent_back, child_back, T_back) in zip(graph.edges(), back.edges(), strict=True):
        assert (parent, child) == (parent_back, child_back)
        assert np.allclose(T, T_back, atol=1e-15)


def test_a_rig_s_cameras_hang_off_the_rig_frame_with_their_scene_poses():
    scene = IrRigScene(IrRigOptions(camera_count=3))
    cameras = {f"bar{i}": camera for i, camera in enumerate(scene.cameras)}
    message = rig_static_transforms(HEADER, cameras)
    assert [(e.parent_frame, e.child_frame) for e in message.transforms] == [(RIG_FRAME, name) for name in cameras]
    graph = frame_graph([message])
    T_cam0_cam2 = invert(scene.cameras[0].T_rig_camera) @ scene.cameras[2].T_rig_camera
    assert np.allclose(graph.transform("bar0", "bar2"), T_cam0_cam2, atol=1e-12)


def test_messages_from_several_publishers_merge_and_contradictions_are_refused():
    first = StaticTransforms(header=HEADER, transforms=(edge("rig", "cam0", -0.15), edge("rig", "cam1", 0.15)))
    second = StaticTransforms(header=HEADER, transforms=(edge("rig", "cam2", 0.45), edge("cam0", "cam1", 0.3)))
    graph = frame_graph([first, second])
    assert np.allclose(graph.transform("cam0", "cam2")[:3, 3], (0.6, 0.0, 0.0))
    clash = StaticTransforms(header=HEADER, transforms=(edge("cam2", "cam1", 0.2),))
    with pytest.raises(InconsistentCycleError, match="T_cam2_cam1 disagrees"):
        frame_graph([clash], graph)
