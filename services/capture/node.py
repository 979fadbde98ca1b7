"""Capture node: publishes Image + CameraInfo frames from a source at a steady pace.

Until the full capture service lands, the one source is the moving test pattern
(``services.capture.pattern``). Every frame is stamped with the wall-clock time it was
made (``time.time_ns()``) and numbered from 0; its CameraInfo shares the header.
"""

from __future__ import annotations

import time
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from protocol.keys import KeyName
from protocol.message import Header
from protocol.sensors import CameraInfo, Image
from services.capture.pattern import DEFAULT_K, render_pattern
from services.runtime.node import Node
from services.runtime.pubsub import Role

SETTLE_S = 0.3
"""Pause after the first subscriber appears, so its own outputs reach their subscribers too."""


class Params(BaseModel):
    """Settings of a pattern source."""

    model_config = ConfigDict(extra="forbid")

    source: Literal["synthetic:pattern"] = "synthetic:pattern"
    camera: KeyName = "cam0"
    fps: float = Field(default=30.0, gt=0, le=1000)
    frames: int = Field(default=0, ge=0, description="stop after this many frames; 0 = run until stopped")
    width: int = Field(default=640, ge=32, le=8192)
    height: int = Field(default=480, ge=32, le=8192)
    wait_for_subscriber: bool = Field(
        default=False, description="hold the first frame until something subscribes to the images")


def run(node: Node, params: Params) -> None:
    images = node.publisher(node.keys.image(params.camera), Image, Role.FRAME)
    infos = node.publisher(node.keys.camera_info(params.camera), CameraInfo, Role.RESULT)
    if params.wait_for_subscriber:
        while node.running and not images.matched():
            node.wait(0.02)
        node.wait(SETTLE_S)
    period = 1.0 / params.fps
    next_at = time.monotonic()
    index = 0
    while node.running and (params.frames == 0 or index < params.frames):
        started = time.perf_counter()
        header = Header(stamp_ns=time.time_ns(), frame_id=params.camera, seq=index)
        images.put(Image(header=header, encoding="mono8",
                         data=render_pattern(index, params.width, params.height)))
        infos.put(CameraInfo(header=header, width=params.width, height=params.height, k=DEFAULT_K,
                             d=(0.0, 0.0, 0.0, 0.0, 0.0)))
        node.processed(time.perf_counter() - started)
        index += 1
        next_at += period
        node.wait(next_at - time.monotonic())
