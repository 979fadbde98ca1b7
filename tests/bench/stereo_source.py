"""The stereo benchmark's source: pre-rendered ``ir_rig`` frame pairs published at a set rate.

``python -m tests.bench.stereo_source RATE FRAMES [CAMERAS]`` (bus settings from the environment,
as a node's): renders ``RENDERED`` instants of the scene first, waits for every camera's image to
have a subscriber, then publishes ``FRAMES`` instants at ``RATE`` Hz, cycling through the rendered
ones, as the capture node does: per camera an ``Image`` (FRAME role) and its ``CameraInfo`` (with
``T_rig_camera``), both cameras of one instant under one header (stamp = wall clock when it goes
out, seq). Rendering is kept out of the timed loop so that the source keeps the rate. At the end it
prints one JSON line: instants sent, the rate reached and how many went out more than a period late.
"""

from __future__ import annotations

import json
import sys
import time

from protocol.message import Header
from protocol.sensors import CameraInfo, Image
from services.bus.pubsub import Publisher, Role
from services.bus.session import BusConfig, open_session
from services.capture.scenes import make_scene
from services.convert import camera_info

RENDERED = 240
SETTLE_S = 0.5
START_S = 30.0


def main(rate: float, frames: int, cameras: int) -> dict[str, float]:
    scene = make_scene("ir_rig", camera_count=cameras)
    rendered = [scene.render(i).images for i in range(RENDERED)]
    bus = BusConfig.from_env()
    session = open_session(bus)
    keys = bus.keys
    names = [camera.name for camera in scene.cameras]
    images = {name: Publisher(session, keys.image(name), Image, Role.FRAME) for name in names}
    infos = {name: Publisher(session, keys.camera_info(name), CameraInfo, Role.RESULT) for name in names}
    try:
        deadline = time.monotonic() + START_S
        while not all(p.matched() for p in images.values()) and time.monotonic() < deadline:
            time.sleep(0.02)
        time.sleep(SETTLE_S)
        period, late = 1.0 / rate, 0
        started = time.monotonic()
        for seq in range(frames):
            due = started + seq * period
            while (wait := due - time.monotonic()) > 0:
                time.sleep(wait)
            late += time.monotonic() - due > period
            stamp = time.time_ns()
            pair = rendered[seq % RENDERED]
            for camera in scene.cameras:
                header = Header(stamp_ns=stamp, frame_id=camera.name, seq=seq)
                images[camera.name].put(Image(header=header, encoding="mono8", data=pair[camera.name]))
                infos[camera.name].put(camera_info(header, camera))
        elapsed = time.monotonic() - started
    finally:
        for publisher in (*images.values(), *infos.values()):
            publisher.close()
        session.close()
    return {"sent": frames, "rate_hz": round(frames / elapsed, 1), "late": late}


if __name__ == "__main__":
    arguments = sys.argv[1:]
    print(json.dumps(main(float(arguments[0]), int(arguments[1]), int(arguments[2]) if len(arguments) > 2 else 2)),
          flush=True)
