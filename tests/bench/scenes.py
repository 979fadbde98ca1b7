"""Render speed of the synthetic scenes, single-threaded: ``bench_scenes()`` -> one JSON-able dict per figure.

Each scene renders consecutive frames at 640 x 480 with its default options, then with noise
and blur on (the post-processing every camera pays for), after a short warm-up; the figure
is the best of ``REPEATS`` timed runs (the least disturbed by the rest of the machine).
``fps`` counts rendered camera images per second; for the multi-camera ``ir_rig`` a second
figure counts whole rig frames (every camera of one index). OpenCV is held to one thread for
the measurement and restored afterwards. ``python -m tests.bench.scenes`` prints the lines.
"""

from __future__ import annotations

import json
import time
from typing import Any

from services.synthetic import make_scene
from tests.bench.blobs import one_opencv_thread

WIDTH, HEIGHT = 640, 480
TARGET_FPS = {"markers": 100, "planar_target": 100, "ir_rig": 100, "room": 30}
FRAMES = {"markers": 200, "planar_target": 200, "ir_rig": 200, "room": 60}
VARIANTS: dict[str, dict[str, Any]] = {"default": {}, "noise_blur": {"noise_std": 2.0, "blur_px": 0.8}}
WARMUP, REPEATS = 5, 3


def frames_per_second(scene, frames: int) -> float:
    """Best rate over ``REPEATS`` runs of ``frames`` consecutive renders (after a warm-up)."""
    for index in range(WARMUP):
        scene.render(index)
    best = float("inf")
    for _ in range(REPEATS):
        started = time.perf_counter()
        for index in range(frames):
            scene.render(index)
        best = min(best, time.perf_counter() - started)
    return frames / best


def bench_scenes() -> list[dict[str, Any]]:
    """One figure per scene and variant (two for ir_rig: per camera and per rig)."""
    with one_opencv_thread():
        lines = []
        for scene_name, target in TARGET_FPS.items():
            for variant, options in VARIANTS.items():
                scene = make_scene(scene_name, width=WIDTH, height=HEIGHT, **options)
                rig_fps = frames_per_second(scene, FRAMES[scene_name])
                cameras = len(scene.cameras)
                common = {"bench": "scene_render", "scene": scene_name, "variant": variant, "options": options,
                          "target_fps": target, "width": WIDTH, "height": HEIGHT, "cameras": cameras}
                lines.append({**common, "per": "camera", "fps": round(rig_fps * cameras, 1)})
                if cameras > 1:
                    lines.append({**common, "per": "rig", "fps": round(rig_fps, 1)})
        return lines


def yardstick() -> float:
    """The room scene's render rate, one OpenCV thread, in frames per second: how fast this machine runs
    CPU-bound work at the moment (the shared VM's speed moves from day to day), printed beside figures of
    other benchmarks so runs of different days can be compared."""
    with one_opencv_thread():
        return round(frames_per_second(make_scene("room", width=WIDTH, height=HEIGHT), FRAMES["room"]), 1)


if __name__ == "__main__":
    for line in bench_scenes():
        print(json.dumps(line), flush=True)
