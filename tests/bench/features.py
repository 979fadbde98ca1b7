"""Image-target speed and accuracy per 640x480 frame, single-threaded OpenCV, in one process, side by
side with OpenCV's per-frame recipes.

On every second frame of the first ``2 * FRAMES`` of the synthetic ``planar_target`` scene (its own
texture as an ORB target, the default), each frame is run in turn through every variant:

* ``baseline_sift``: ``tests.feature_baseline.SiftBaseline`` (SIFT, L2 ratio test, USAC_MAGSAC,
  ``solvePnP`` IPPE), the reference image described once beforehand;
* ``baseline_orb``: ``tests.feature_baseline.OrbBaseline``, the same recipe with ORB at OpenCV's
  defaults and Hamming matching: the fastest stock recipe;
* ``recognition``: ``TargetRecognizer.recognise_image`` from scratch (keypoints, matching through the
  target's hashing index, homography, pose);
* ``recognition_bruteforce``: the same with the Hamming brute-force matcher;
* ``tracking``: ``TargetTracker.track`` at the default options, the frames in order (after the first
  frame's recognition every frame is followed on; a frame that falls back to recognition counts as it
  costs).

Figures: ms per frame p50 / p99 after ``WARMUP`` frames, frames a second at the p50, how many frames
each variant posed and its errors against the scene's truth over every frame it posed (rotation deg,
translation % of the distance: median and p90), and the ratios baseline p50 / ours p50 for both
baselines, those of tracking with the target ``TARGET_SPEEDUP``. ``python -m tests.bench.features``
prints the lines.
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
from services.geometry.evaluation import pose_error
from services.synthetic import make_scene
from tests.bench.blobs import one_opencv_thread, per_frame_us
from tests.feature_baseline import Baseline, OrbBaseline, SiftBaseline

WIDTH, HEIGHT = 640, 480
FRAMES = 75
FPS = 30.0
TARGET_SPEEDUP = 4.0
BASELINES = ("baseline_sift", "baseline_orb")
OURS = ("recognition", "tracking")

Poses = dict[str, list[np.ndarray | None]]
"""Per variant, each frame's ``T_camera_target`` (4, 4) in the order run (None: not posed)."""


def bench_features() -> list[dict[str, Any]]:
    with one_opencv_thread():
        scene = make_scene("planar_target", width=WIDTH, height=HEIGHT)
        camera = scene.cameras[0]
        rendered = [scene.render(2 * i) for i in range(FRAMES)]
        frames = [frame.images[camera.name] for frame in rendered]
        truth = [frame.truth[camera.name][0][2] for frame in rendered]
        width_m = scene.size_m[0]
        target = build_target("poster", scene.texture, width_m)
        bruteforce = TargetRecognizer(target)
        bruteforce.matcher = make_matcher(True, exact=True)
        bruteforce.matcher.add([target.descriptors])
        poses: Poses = {name: [] for name in (*BASELINES, "recognition", "recognition_bruteforce", "tracking")}
        variants = {
            "baseline_sift": _baseline(SiftBaseline(scene.texture), width_m, camera.K, poses["baseline_sift"]),
            "baseline_orb": _baseline(OrbBaseline(scene.texture), width_m, camera.K, poses["baseline_orb"]),
            "recognition": _recognition(TargetRecognizer(target), camera.K, poses["recognition"]),
            "recognition_bruteforce": _recognition(bruteforce, camera.K, poses["recognition_bruteforce"]),
            "tracking": _tracking(TargetTracker(target), camera.K, poses["tracking"]),
        }
        times = per_frame_us(variants, frames)
        common = {"bench": "features", "width": WIDTH, "height": HEIGHT, "frames": FRAMES, "threads": 1,
                  "target_keypoints": len(target.keypoints)}
        p50 = {name: float(np.percentile(values, 50)) / 1e3 for name, values in times.items()}
        lines = [{**common, "variant": name, "p50_ms": round(p50[name], 2),
                  "p99_ms": round(float(np.percentile(values, 99)) / 1e3, 2),
                  "fps_at_p50": round(1e3 / p50[name], 1), **_accuracy(poses[name], truth)}
                 for name, values in times.items()]
        for baseline in BASELINES:
            for ours in OURS:
                speedup = p50[baseline] / p50[ours]
                line = {**common, "figure": f"{baseline}_over_{ours}_p50", "ratio": round(speedup, 2)}
                if ours == "tracking":
                    line |= {"target": f">= {TARGET_SPEEDUP}", "met": speedup >= TARGET_SPEEDUP}
                lines.append(line)
        return lines


def _accuracy(poses: list[np.ndarray | None], truth: list[np.ndarray]) -> dict[str, Any]:
    """Frames posed, and the median and p90 of the rotation error (deg) and of the translation error (% of
    the true distance) over them, each (4, 4) ``T_camera_target`` against the true one of its frame."""
    errors = np.array([(np.degrees(angle), 100 * distance / np.linalg.norm(T_true[:3, 3]))
                       for T, T_true in zip(poses, truth, strict=True) if T is not None
                       for angle, distance in [pose_error(T, T_true)]]).reshape(-1, 2)
    figures: dict[str, Any] = {"posed": len(errors)}
    for column, name in enumerate(("rotation_deg", "translation_pct")):
        median, p90 = np.percentile(errors[:, column], [50, 90]) if len(errors) else (np.nan, np.nan)
        figures |= {f"{name}_median": round(float(median), 4), f"{name}_p90": round(float(p90), 4)}
    return figures


def _baseline(baseline: Baseline, width_m: float, K: np.ndarray,
              poses: list[np.ndarray | None]) -> Callable[[np.ndarray], None]:
    """OpenCV's recipe posing the target ``width_m`` wide in every frame, from scratch."""
    return lambda image: poses.append(baseline.pose(image, width_m, K))


def _tracking(tracker: TargetTracker, K: np.ndarray, poses: list[np.ndarray | None]) -> Callable[[np.ndarray], None]:
    """The tracker following the target through frames given in order, stamped ``FPS`` apart."""
    count = iter(range(10**9))
    return lambda image: poses.append(tracker.track(image, K, None, round(next(count) * 1e9 / FPS)).T_camera_target)


def _recognition(recognizer: TargetRecognizer, K: np.ndarray,
                 poses: list[np.ndarray | None]) -> Callable[[np.ndarray], None]:
    """A variant recognising the target from scratch in every frame."""
    extract = make_extractor(recognizer.target.detector)
    return lambda image: poses.append(recognizer.recognise_image(image, K, None, extract).T_camera_target)


if __name__ == "__main__":
    for line in bench_features():
        print(json.dumps(line), flush=True)
