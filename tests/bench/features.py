"""Image-target speed per 640x480 frame, single-threaded OpenCV, in one process, side by side with
OpenCV's per-frame recipe.

On every second frame of the first ``2 * FRAMES`` of the synthetic ``planar_target`` scene (its own
texture as an ORB target, the default), each frame is run in turn through every variant:

* ``baseline``: ``tests.feature_baseline`` (SIFT, ratio test, USAC_MAGSAC, ``solvePnP`` IPPE), the
  reference image described once beforehand;
* ``recognition``: ``TargetRecognizer.recognise_image`` from scratch (keypoints, matching through the
  target's hashing index, homography, pose);
* ``recognition_bruteforce``: the same with the Hamming brute-force matcher;
* ``tracking``: ``TargetTracker.track`` at the default options, the frames in order (after the first
  frame's recognition every frame is followed on; a frame that falls back to recognition counts as it
  costs).

Figures: ms per frame p50 / p99 after ``WARMUP`` frames, frames a second at the p50, how many frames
each variant posed, and the ratios baseline p50 / ours p50 with the tracker's target
``TARGET_SPEEDUP``. ``python -m tests.bench.features`` prints the lines.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from typing import Any

import numpy as np

from services.estimation.targets.features import make_extractor
from services.estimation.targets.recognition import TargetRecognizer, make_matcher
from services.estimation.targets.target import build_target
from services.estimation.targets.tracking import TargetTracker
from services.synthetic import make_scene
from tests.bench.blobs import one_opencv_thread, per_frame_us
from tests.feature_baseline import SiftBaseline

WIDTH, HEIGHT = 640, 480
FRAMES = 75
FPS = 30.0
TARGET_SPEEDUP = 4.0


def bench_features() -> list[dict[str, Any]]:
    with one_opencv_thread():
        scene = make_scene("planar_target", width=WIDTH, height=HEIGHT)
        camera = scene.cameras[0]
        frames = [scene.render(2 * i).images[camera.name] for i in range(FRAMES)]
        width_m = scene.size_m[0]
        target = build_target("poster", scene.texture, width_m)
        baseline = SiftBaseline(scene.texture)
        bruteforce = TargetRecognizer(target)
        bruteforce.matcher = make_matcher(True, exact=True)
        bruteforce.matcher.add([target.descriptors])
        posed = dict.fromkeys(("baseline", "recognition", "recognition_bruteforce", "tracking"), 0)
        variants = {
            "baseline": _counted(lambda image: baseline.pose(image, width_m, camera.K) is not None,
                                 posed, "baseline"),
            "recognition": _recognition(TargetRecognizer(target), camera.K, posed, "recognition"),
            "recognition_bruteforce": _recognition(bruteforce, camera.K, posed, "recognition_bruteforce"),
            "tracking": _tracking(TargetTracker(target), camera.K, posed),
        }
        times = per_frame_us(variants, frames)
        common = {"bench": "features", "width": WIDTH, "height": HEIGHT, "frames": FRAMES, "threads": 1,
                  "target_keypoints": len(target.keypoints)}
        p50 = {name: float(np.percentile(values, 50)) / 1e3 for name, values in times.items()}
        lines = [{**common, "variant": name, "p50_ms": round(p50[name], 2),
                  "p99_ms": round(float(np.percentile(values, 99)) / 1e3, 2),
                  "fps_at_p50": round(1e3 / p50[name], 1), "posed": posed[name]} for name, values in times.items()]
        for ours in ("recognition", "tracking"):
            speedup = p50["baseline"] / p50[ours]
            line = {**common, "figure": f"baseline_over_{ours}_p50", "ratio": round(speedup, 2)}
            if ours == "tracking":
                line |= {"target": f">= {TARGET_SPEEDUP}", "met": speedup >= TARGET_SPEEDUP}
            lines.append(line)
        return lines


def _counted(posed_one: Callable[[np.ndarray], bool], posed: dict[str, int], name: str) -> Callable[[np.ndarray], bool]:
    """A variant that adds each frame it posed to ``posed[name]``."""

    def run(image: np.ndarray) -> bool:
        found = posed_one(image)
        posed[name] += found
        return found

    return run


def _tracking(tracker: TargetTracker, K: np.ndarray, posed: dict[str, int]) -> Callable[[np.ndarray], bool]:
    """The tracker following the target through frames given in order, stamped ``FPS`` apart."""
    count = iter(range(10**9))
    return _counted(lambda image: tracker.track(image, K, None, round(next(count) * 1e9 / FPS)).posed,
                    posed, "tracking")


def _recognition(recognizer: TargetRecognizer, K: np.ndarray, posed: dict[str, int],
                 name: str) -> Callable[[np.ndarray], bool]:
    """A variant recognising the target from scratch in every frame."""
    extract = make_extractor(recognizer.target.detector)
    return _counted(lambda image: recognizer.recognise_image(image, K, None, extract).recognised, posed, name)


if __name__ == "__main__":
    for line in bench_features():
        print(json.dumps(line), flush=True)
