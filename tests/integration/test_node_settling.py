"""A node's set-up is left out of later full collections once the node serves: what it built before it took
its first input (a scene, detectors, compiled kernels) is frozen then, not only what existed as it started,
so no full collection walks it again in the middle of its frames (a real node on a real Zenoh session)."""

from __future__ import annotations

import gc

import pytest

from protocol.sensors import Image
from services.bus.pubsub import Role
from services.runtime.node import Node

pytestmark = pytest.mark.integration


def test_what_a_node_builds_before_it_serves_is_frozen_once_it_does(bus):
    node = Node("settling", "test", bus.config)
    gc.unfreeze()
    try:
        built = [["a detector's tables"] for _ in range(100)]  # made by the node's body before its loop
        assert any(obj is built[0] for obj in gc.get_objects())
        frames = node.inbox(node.keys.image("cam0"), Image, Role.FRAME)
        node.stop()
        assert list(node.inputs(frames)) == []  # serving starts, and ends at once: the node was stopped
        assert node.serving.is_set()
        assert not any(obj is built[0] for obj in gc.get_objects())  # frozen: no generation holds it
        later = ["built while serving"]
        node.ready()
        assert any(obj is later for obj in gc.get_objects())  # settled once only: later objects are collected
    finally:
        gc.unfreeze()
        node.close()
