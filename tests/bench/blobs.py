"""Blob detection speed per 640x480 frame, single-threaded OpenCV.

* ``ir``: ``detect_ir_blobs`` on frames of the synthetic ``ir_rig`` scene (``BODIES`` bodies, so
  about 20 blobs a frame, with sensor noise), against ``cc_plain``: ``cv2.threshold`` and
  ``cv2.connectedComponentsWithStats`` alone on the same frames (components, areas and unweighted
  centroids, no shape, no flags). ``ratio`` = ir p50 / cc_plain p50. Target: ir p50 under 1 ms.
* ``log``: ``detect_log_blobs`` (default 12 scales) on the same frames, beside OpenCV's
  ``SimpleBlobDetector`` (``simple_blob``) with bright blobs.
* ``colour``: ``detect_colour_blobs`` on a BGR frame of ``COLOUR_DISCS`` coloured discs.

Each frame is run through every variant back to back (a slow spell of the machine hits them
alike); figures are the per-frame p50 / p99 in microseconds after ``WARMUP`` frames.
``python -m tests.bench.blobs`` prints the lines.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

import cv2
import numpy as np

from services.detection.blobs.bright import IrBlobParams, detect_ir_blobs
from services.detection.blobs.colour import HueModel, detect_colour_blobs
from services.detection.blobs.scale_space import detect_log_blobs
from services.synthetic import make_scene

WIDTH, HEIGHT = 640, 480
FRAMES, LOG_FRAMES, WARMUP = 300, 20, 5
BODIES = 4
NOISE_STD = 2.0
TARGET_IR_MS = 1.0
COLOUR_DISCS = 20


def per_frame_us(variants: dict[str, Callable[[np.ndarray], object]], frames: list[np.ndarray]) -> dict[str, list]:
    """Microseconds per frame for each variant, every frame run through all variants in turn."""
    times: dict[str, list[float]] = {name: [] for name in variants}
    for frame in frames:
        for name, run in variants.items():
            started = time.perf_counter()
            run(frame)
            times[name].append((time.perf_counter() - started) * 1e6)
    return {name: values[WARMUP:] for name, values in times.items()}


@contextmanager
def one_opencv_thread() -> Iterator[None]:
    """OpenCV on one thread inside the block (per-frame figures of one core), as many as before after it."""
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        yield
    finally:
        cv2.setNumThreads(threads)


def figures(values: list[float]) -> dict[str, float]:
    p50, p99 = np.percentile(values, [50, 99])
    return {"p50_us": round(float(p50), 1), "p99_us": round(float(p99), 1)}


def colour_frame(rng: np.random.Generator) -> tuple[np.ndarray, tuple[int, int, int, int]]:
    """(H, W, 3) BGR frame of red, green and blue discs on grey with noise, and a sample rectangle on a red one."""
    image = np.full((HEIGHT, WIDTH, 3), 110, np.uint8)
    colours = ((30, 20, 210), (40, 190, 30), (200, 60, 20))
    for k in range(COLOUR_DISCS):
        centre = (int(40 + 112 * (k % 5) + rng.integers(-10, 10)), int(50 + 110 * (k // 5) + rng.integers(-10, 10)))
        cv2.circle(image, centre, int(rng.integers(8, 30)), colours[k % 3], -1, cv2.LINE_AA)
    image = cv2.add(image, rng.normal(0, 3, image.shape).astype(np.int16), dtype=cv2.CV_8U)
    return image, (35, 45, 10, 10)


def bench_blobs() -> list[dict[str, Any]]:
    with one_opencv_thread():
        scene = make_scene("ir_rig", width=WIDTH, height=HEIGHT, body_count=BODIES, noise_std=NOISE_STD)
        camera = scene.cameras[0].name
        frames = [scene.render(i).images[camera] for i in range(FRAMES)]
        params = IrBlobParams()
        blobs = [len(detect_ir_blobs(frame, params)) for frame in frames]
        ir = per_frame_us({
            "ir": lambda frame: detect_ir_blobs(frame, params),
            "cc_plain": lambda frame: cv2.connectedComponentsWithStats(
                cv2.threshold(frame, params.threshold, 255, cv2.THRESH_BINARY)[1], connectivity=8),
        }, frames)
        bright = cv2.SimpleBlobDetector_Params()
        bright.blobColor = 255
        simple = cv2.SimpleBlobDetector_create(bright)
        log = per_frame_us({"log": detect_log_blobs, "simple_blob": simple.detect}, frames[:LOG_FRAMES + WARMUP])
        image, rect = colour_frame(np.random.default_rng(0))
        model = HueModel.from_sample(image, rect)
        colour = per_frame_us({"colour": lambda frame: detect_colour_blobs(frame, model)},
                              [image] * (LOG_FRAMES + WARMUP))
        common = {"bench": "blob_detection", "width": WIDTH, "height": HEIGHT}
        ir_frames = {"frames": len(frames) - WARMUP, "blobs_mean": round(float(np.mean(blobs)), 1)}
        ratio = figures(ir["ir"])["p50_us"] / figures(ir["cc_plain"])["p50_us"]
        return [
            {**common, "variant": "ir", **figures(ir["ir"]), **ir_frames,
             "target_p50_ms": TARGET_IR_MS, "met": figures(ir["ir"])["p50_us"] < TARGET_IR_MS * 1e3},
            {**common, "variant": "cc_plain", **figures(ir["cc_plain"]), **ir_frames},
            {**common, "figure": "ir_vs_cc_plain_p50", "ratio": round(ratio, 3)},
            {**common, "variant": "log", **figures(log["log"]), "frames": LOG_FRAMES},
            {**common, "variant": "simple_blob", **figures(log["simple_blob"]), "frames": LOG_FRAMES},
            {**common, "variant": "colour", **figures(colour["colour"]), "frames": LOG_FRAMES,
             "discs": COLOUR_DISCS},
        ]


if __name__ == "__main__":
    for line in bench_blobs():
        print(json.dumps(line), flush=True)
