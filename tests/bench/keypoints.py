"""Keypoint detection speed per 640x480 frame, single-threaded OpenCV.

Every method of ``services.detection.keypoints.detector`` (``orb``, ``sift``, ``akaze``, ``harris``,
``shi_tomasi``) with its own descriptors, on frames of the synthetic ``planar_target`` scene,
capped at ``MAX_COUNT`` keypoints spread by grid bucketing (the node's default); beside them
ORB with TEBLID descriptors, ORB spread by ANMS and without spreading, and OpenCV's plain
``ORB_create(MAX_COUNT).detectAndCompute`` (``orb_plain``) as a baseline.

Each frame is run through every variant back to back (a slow spell of the machine hits them
alike); figures are the per-frame p50 / p99 in milliseconds after ``WARMUP`` frames, with the
mean count of keypoints. ``python -m tests.bench.keypoints`` prints the lines.
"""

from __future__ import annotations

import json
from typing import Any

import cv2
import numpy as np

from services.detection.grey import as_grey8
from services.detection.keypoints.detector import METHODS, KeypointDetector, KeypointParams
from services.synthetic import make_scene
from tests.bench.blobs import WARMUP, one_opencv_thread, per_frame_us

WIDTH, HEIGHT = 640, 480
FRAMES = 25
MAX_COUNT = 1000


def bench_keypoints() -> list[dict[str, Any]]:
    with one_opencv_thread():
        scene = make_scene("planar_target", width=WIDTH, height=HEIGHT)
        camera = scene.cameras[0].name
        frames = [as_grey8(scene.render(i).images[camera]) for i in range(FRAMES + WARMUP)]
        detectors = {method: KeypointDetector(KeypointParams(method=method, max_count=MAX_COUNT)) for method in METHODS}
        detectors["orb_teblid"] = KeypointDetector(KeypointParams(descriptor="teblid", max_count=MAX_COUNT))
        detectors["orb_anms"] = KeypointDetector(KeypointParams(spread="anms", max_count=MAX_COUNT))
        detectors["orb_unspread"] = KeypointDetector(KeypointParams(spread="none", max_count=MAX_COUNT))
        counts = {name: np.mean([len(d.detect(f)) for f in frames[:WARMUP]]) for name, d in detectors.items()}
        plain = cv2.ORB.create(MAX_COUNT)
        variants = {name: d.detect for name, d in detectors.items()}
        variants["orb_plain"] = lambda frame: plain.detectAndCompute(frame, None)
        counts["orb_plain"] = np.mean([len(plain.detect(f, None)) for f in frames[:WARMUP]])
        times = per_frame_us(variants, frames)
        common = {"bench": "keypoints", "width": WIDTH, "height": HEIGHT, "frames": FRAMES, "max_count": MAX_COUNT}
        return [{**common, "variant": name, "p50_ms": round(float(np.percentile(values, 50)) / 1e3, 2),
                 "p99_ms": round(float(np.percentile(values, 99)) / 1e3, 2),
                 "keypoints_mean": round(float(counts[name]), 1)} for name, values in times.items()]


if __name__ == "__main__":
    for line in bench_keypoints():
        print(json.dumps(line), flush=True)
