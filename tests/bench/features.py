"""Natural-feature target speed per 640x480 frame, single-threaded OpenCV, side by side with OpenCV's
per-frame recipe.

On ``FRAMES`` consecutive frames of the synthetic ``planar_target`` scene (the target built from its
texture, ORB, the default), each frame is run in turn through:

* ``baseline``: ``tests.feature_baseline`` (SIFT, ratio test, USAC_MAGSAC, ``solvePnP`` IPPE), the
  reference image described once beforehand;
* ``recognition``: ``TargetRecognizer.recognise_image`` (keypoints, matching, homography, pose);
* ``tracking``: ``TargetTracker.track``, the frames in order (after the first, recognised, frame the
  points are followed; a frame that falls back to recognition counts as it costs).

Figures: per-frame p50 / p99 in milliseconds after ``WARMUP`` frames, frames a second at the p50, and
the ratios baseline p50 / ours p50, with the tracker's target ``TARGET_SPEEDUP`` (at least 4 times the
baseline's speed). ``python -m tests.bench.features`` prints the lines.
"""

from __future__ import annotations

import json
from typing import Any

import cv2
import numpy as np

from services.capture.scenes import make_scene
from services.estimation.target_features import make_extractor
from services.estimation.target_recognition import TargetRecognizer
from services.estimation.target_tracking import TargetTracker
from services.estimation.targets import build_target
from tests.bench.blobs import WARMUP, per_frame_us
from tests.feature_baseline import SiftBaseline

WIDTH, HEIGHT = 640, 480
FRAMES = 60
TARGET_SPEEDUP = 4.0


def bench_features() -> list[dict[str, Any]]:
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        scene = make_scene("planar_target", width=WIDTH, height=HEIGHT)
        K = scene.cameras[0].K
        frames = [scene.render(i) for i in range(FRAMES + WARMUP)]
        images = [frame.images["cam0"] for frame in frames]
        stamps = iter([round(frame.time_s * 1e9) for frame in frames])
        target = build_target("poster", scene.texture, scene.size_m[0])
        recognizer, tracker = TargetRecognizer(target), TargetTracker(target)
        extract = make_extractor(target.detector)
        baseline = SiftBaseline(scene.texture)
        states: list[str] = []

        def track(image: np.ndarray) -> None:
            states.append(tracker.track(image, K, None, next(stamps)).state.value)

        times = per_frame_us({
            "baseline": lambda image: baseline.pose(image, scene.size_m[0], K),
            "recognition": lambda image: recognizer.recognise_image(image, K, None, extract),
            "tracking": track,
        }, images)
        p50 = {name: float(np.percentile(values, 50)) / 1e3 for name, values in times.items()}
        common = {"bench": "features", "width": WIDTH, "height": HEIGHT, "frames": FRAMES}
        lines = [{**common, "variant": name, "p50_ms": round(p50[name], 2),
                  "p99_ms": round(float(np.percentile(values, 99)) / 1e3, 2),
                  "frames_per_s_p50": round(1e3 / p50[name], 1)} for name, values in times.items()]
        lines[-1] |= {"recognised": states.count("recognised"), "lost": states.count("lost")}
        for ours in ("recognition", "tracking"):
            speedup = p50["baseline"] / p50[ours]
            line = {**common, "figure": f"baseline_over_{ours}_p50", "ratio": round(speedup, 2)}
            if ours == "tracking":
                line |= {"target": f">= {TARGET_SPEEDUP}", "met": speedup >= TARGET_SPEEDUP}
            lines.append(line)
        return lines
    finally:
        cv2.setNumThreads(threads)


if __name__ == "__main__":
    for line in bench_features():
        print(json.dumps(line), flush=True)
