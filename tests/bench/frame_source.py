"""The pipeline benchmarks' source: a scene's pre-rendered frames published at a set rate.

``python -m tests.bench.frame_source SCENE RATE FRAMES [--rendered N] [NAME=VALUE ...]`` (bus settings
from the environment, as a node's; ``NAME=VALUE`` are the scene's options): renders ``N`` instants of
the scene first (default ``RENDERED``), waits for every camera's image to have a subscriber, then
publishes ``FRAMES`` instants at ``RATE`` Hz, cycling through the rendered ones, as the capture node
does: per camera an ``Image`` (FRAME role) and its ``CameraInfo`` (with ``T_rig_camera``), every
camera of one instant under one header (stamp = wall clock when it goes out, seq). Rendering is kept
out of the timed loop so that the source keeps the rate. At the end it prints one JSON line: instants
sent, the rate reached and how many went out more than a period late.
"""

from __future__ import annotations

import argparse
import json
import time

from protocol.message import Header
from protocol.sensors import CameraInfo, Image
from services.bus.pubsub import Publisher, Role
from services.bus.session import BusConfig, open_session
from services.convert import camera_info
from services.synthetic import make_scene, scene_options

RENDERED = 240
SETTLE_S = 0.5
START_S = 30.0


def main(scene_name: str, rate: float, frames: int, rendered: int = RENDERED,
         options: dict[str, object] | None = None) -> dict[str, float]:
    scene = make_scene(scene_name, **scene_options(scene_name, options or {}))
    instants = [scene.render(i).images for i in range(rendered)]
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
            instant = instants[seq % rendered]
            for camera in scene.cameras:
                header = Header(stamp_ns=stamp, frame_id=camera.name, seq=seq)
                images[camera.name].put(Image(header=header, encoding="mono8", data=instant[camera.name]))
                infos[camera.name].put(camera_info(header, camera))
        elapsed = time.monotonic() - started
    finally:
        for publisher in (*images.values(), *infos.values()):
            publisher.close()
        session.close()
    return {"sent": frames, "rate_hz": round(frames / elapsed, 1), "late": late}


def source_argv(scene: str, rate: float, frames: int, rendered: int = RENDERED, **options: object) -> list[str]:
    """The arguments after ``python -m tests.bench.frame_source`` that run ``main`` with these."""
    return [scene, str(rate), str(frames), *(f"{k}={v}" for k, v in options.items()), "--rendered", str(rendered)]


def _parse(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="python -m tests.bench.frame_source",
                                     description="publish a scene's pre-rendered frames at a set rate")
    parser.add_argument("scene")
    parser.add_argument("rate", type=float)
    parser.add_argument("frames", type=int)
    parser.add_argument("--rendered", type=int, default=RENDERED, help="instants rendered beforehand and cycled")
    parser.add_argument("options", nargs="*", metavar="NAME=VALUE", help="the scene's options")
    return parser.parse_args(argv)


if __name__ == "__main__":
    args = _parse()
    chosen = dict(option.split("=", 1) for option in args.options)
    print(json.dumps(main(args.scene, args.rate, args.frames, args.rendered, chosen)), flush=True)
