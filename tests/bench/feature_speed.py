"""Image-target speed per 640x480 frame, single-threaded OpenCV, in one process.

On every second frame of the first ``2 * FRAMES`` of the synthetic ``planar_target`` scene (its
own texture as an ORB target), side by side, each frame through every variant in turn:

* ``tracking``: ``TargetTracker.track`` at the default options, frame after frame (after the
  first frame's recognition every frame is followed on);
* ``recognition``: ``TargetRecognizer.recognise_image`` from scratch (keypoints, matching through
  the target's hashing index, homography, pose);
* ``recognition_bruteforce``: the same with the Hamming brute-force matcher.

Figures: ms per frame p50 / p99 after ``WARMUP`` frames, frames per second at the p50, and how many
frames each variant gave a pose. ``python -m tests.bench.feature_speed`` prints the lines.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from typing import Any

import cv2
import numpy as np

from services.capture.scenes import make_scene
from services.estimation.target_features import make_extractor
from services.estimation.target_recognition import TargetRecognizer, make_matcher
from services.estimation.target_tracking import TargetTracker
from services.estimation.targets import build_target
from tests.bench.blobs import per_frame_us

WIDTH, HEIGHT = 640, 480
FRAMES = 75
FPS = 30.0


def bench_feature_speed() -> list[dict[str, Any]]:
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        scene = make_scene("planar_target", width=WIDTH, height=HEIGHT)
        camera = scene.cameras[0]
        frames = [scene.render(2 * i).images[camera.name] for i in range(FRAMES)]
        target = build_target("poster", scene.texture, scene.size_m[0])
        posed = {name: 0 for name in ("tracking", "recognition", "recognition_bruteforce")}
        variants = {"tracking": _tracking(TargetTracker(target), camera.K, posed),
                    "recognition": _recognition(TargetRecognizer(target), camera.K, posed, "recognition")}
        bruteforce = TargetRecognizer(target)
        bruteforce.matcher = make_matcher(True, exact=True)
        bruteforce.matcher.add([target.descriptors])
        variants["recognition_bruteforce"] = _recognition(bruteforce, camera.K, posed, "recognition_bruteforce")
        times = per_frame_us(variants, frames)
        common = {"bench": "feature_speed", "width": WIDTH, "height": HEIGHT, "frames": FRAMES, "threads": 1,
                  "target_keypoints": len(target.keypoints)}
        lines = []
        for name, values in times.items():
            p50, p99 = (float(v) / 1e3 for v in np.percentile(values, [50, 99]))
            lines.append({**common, "variant": name, "p50_ms": round(p50, 2), "p99_ms": round(p99, 2),
                          "fps_at_p50": round(1e3 / p50, 1), "posed": posed[name]})
        return lines
    finally:
        cv2.setNumThreads(threads)


def _tracking(tracker: TargetTracker, K: np.ndarray, posed: dict[str, int]) -> Callable[[np.ndarray], object]:
    """A variant following the target through frames given in order, stamped ``FPS`` apart (twice the
    scene's frame step)."""
    count = iter(range(10**9))

    def run(image: np.ndarray) -> object:
        pose = tracker.track(image, K, None, round(2 * next(count) * 1e9 / FPS))
        posed["tracking"] += pose.posed
        return pose

    return run


def _recognition(recognizer: TargetRecognizer, K: np.ndarray, posed: dict[str, int],
                 name: str) -> Callable[[np.ndarray], object]:
    """A variant recognising the target from scratch in every frame."""
    extract = make_extractor(recognizer.target.detector)

    def run(image: np.ndarray) -> object:
        result = recognizer.recognise_image(image, K, None, extract)
        posed[name] += result.recognised
        return result

    return run


if __name__ == "__main__":
    for line in bench_feature_speed():
        print(json.dumps(line), flush=True)
