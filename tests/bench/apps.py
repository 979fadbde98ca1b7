"""The marker pipeline's own latency with client apps subscribed, against none, in one run.

The pipeline is ``tests.bench.markers``'s: a capture node renders the synthetic ``markers``
scene (``FRAMES`` frames of 640x480 at ``FPS``), a ``marker_pose`` node detects and estimates.
Two latencies per frame: the pipeline's own, capture stamp -> the node done with the frame
(its poses and detections published), from the node's ``NodeStats``; and capture stamp ->
arrival of the frame's last pose at this process's subscriber, itself one more client. With
apps, ``APPS`` processes of ``examples/track_marker.py`` (``services.client.connect``, a sync
iterator over every pose of the rig, one formatted line per pose to /dev/null) are subscribed
before the first frame, peers meeting the nodes through the same router as apps on one machine
do. The passes run in the order ``PASSES`` (0, 5, 5, 0): a drift of the shared machine hits
both conditions alike. A condition's p50 / p99 are medians over its passes (every pass listed);
the ratios apps / none are medians over the pairs of passes. Target: the pipeline's
own latency p50 moves by no more than ``TARGET_RATIO`` - 1; its p99 ratio and the subscriber's
ratios are reported beside it. The subscriber's figure is not the pipeline's own: on 2 cores
its process competes with the five apps for the CPU at the moment they all receive the same
poses, which is the apps' cost to one another, not to the pipeline.
``python -m tests.bench.apps`` prints the lines (about 80 s).
"""

from __future__ import annotations

import json
import statistics
from typing import Any

from services.detection.markers.settings import DetectorSettings
from tests.bench.figures import paired_median
from tests.bench.markers import FPS, FRAMES, MARKER_LENGTH, pipeline

APPS = 5
PASSES = (0, APPS, APPS, 0)
TARGET_RATIO = 1.1
BENCH = "pipeline_with_apps"


def condition_line(apps: int, passes: list[dict[str, Any]]) -> dict[str, Any]:
    """One condition's medians over its passes; each pass's p50 / p99, the marker node's own
    processing p50 and what the apps received."""
    line = {"bench": BENCH, "apps": apps, "fps": FPS, "frames": FRAMES, "passes": len(passes),
            "latency_p50_ms": round(statistics.median(p["node_latency_p50_ms"] for p in passes), 3),
            "latency_p99_ms": round(statistics.median(p["node_latency_p99_ms"] for p in passes), 3),
            "latency_p50_ms_passes": [round(p["node_latency_p50_ms"], 3) for p in passes],
            "subscriber_p50_ms": round(statistics.median(p["p50_ms"] for p in passes), 3),
            "subscriber_p99_ms": round(statistics.median(p["p99_ms"] for p in passes), 3),
            "subscriber_p50_ms_passes": [p["p50_ms"] for p in passes],
            "node_p50_ms_passes": [round(p["node_p50_ms"], 3) for p in passes],
            "frames_with_poses_min": min(p["frames_with_poses"] for p in passes),
            "dropped": sum(p["dropped"] or 0 for p in passes)}
    if apps:
        line["poses_per_pass"] = [p["poses"] for p in passes]
        line["app_poses_min_per_pass"] = [p["app_poses_min"] for p in passes]
        line["apps_cores_per_pass"] = [p["apps_cores"] for p in passes]
    return line


def bench_apps() -> list[dict[str, Any]]:
    """Both conditions' figures and their ratios (see the module docstring)."""
    settings = DetectorSettings(marker_length=MARKER_LENGTH)
    passes: dict[int, list[dict[str, Any]]] = {0: [], APPS: []}
    for apps in PASSES:
        passes[apps].append(pipeline(settings, apps=apps))
    with_apps, alone = passes[APPS], passes[0]
    def ratio(field: str) -> float:
        return round(paired_median([p[field] for p in with_apps], [p[field] for p in alone]), 3)

    p50 = ratio("node_latency_p50_ms")
    return [condition_line(0, alone), condition_line(APPS, with_apps),
            {"bench": BENCH, "figure": f"{APPS}_apps_vs_none", "latency_p50_ratio": p50,
             "latency_p99_ratio": ratio("node_latency_p99_ms"), "subscriber_p50_ratio": ratio("p50_ms"),
             "subscriber_p99_ratio": ratio("p99_ms"), "target": f"latency p50 ratio <= {TARGET_RATIO}",
             "met": p50 <= TARGET_RATIO}]


if __name__ == "__main__":
    for line in bench_apps():
        print(json.dumps(line), flush=True)
