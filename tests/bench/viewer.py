"""Cost of the viewer, in-process on a file sink: ``bench_viewer()`` -> one JSON-able dict per figure.

Each variant logs its messages through the viewer's own path (``Scene`` + ``ViewLog``: rows,
timelines, ``RecordingStream.log``) into a fresh .rrd in a temporary folder, every message
logged (no rate limit), after ``WARMUP`` untimed ones:

* ``image_raw`` / ``image_jpeg``: 640x480 mono8 frames of the ``markers`` scene with sensor
  noise (sigma 2), raw pixels or ``cv2.imencode`` JPEG at quality ``JPEG_QUALITY``;
* ``pose``: a marker pose with its axes and a 300-point trajectory line (the default length);
* ``markers``: 10 marker outlines with their ids; ``keypoints``: 500 feature points.

Figures: ``log_ms_p50``/``_p99`` of one ``ViewLog.log`` call (what the node's thread spends
per message), ``amortized_ms`` = wall time of all timed messages including the final flush
to disk, divided by their number, and ``bytes_per_msg`` on disk. The target is what keeps
the node far from the pipeline's way: images under ``IMAGE_TARGET_MS`` amortized (four
cameras at 30 fps in half a core), results under ``RESULT_TARGET_MS``.
``python -m tests.bench.viewer`` prints the lines; the whole benchmark takes a few seconds.
"""

from __future__ import annotations

import json
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from protocol import Header, Image, Keypoints, MarkerDetections, Message, Pose, Transform
from services.synthetic import make_scene
from services.viewer.recording import ViewLog, open_recording
from services.viewer.scene import Scene, ViewOptions

WIDTH, HEIGHT = 640, 480
PERIOD_NS = 33_333_333
JPEG_QUALITY = 80
WARMUP = 20
IMAGES, RESULTS = 300, 2000
IMAGE_TARGET_MS, RESULT_TARGET_MS = 4.0, 0.5


def header(i: int) -> Header:
    return Header(stamp_ns=1_700_000_000_000_000_000 + i * PERIOD_NS, frame_id="cam0", seq=i)


def image_maker() -> Callable[[int], Message]:
    scene = make_scene("markers", width=WIDTH, height=HEIGHT, noise_std=2.0)
    frames = [scene.render(i).images["cam0"] for i in range(30)]
    return lambda i: Image(header=header(i), encoding="mono8", data=frames[i % len(frames)])


def pose(i: int) -> Message:
    angle = 0.01 * i
    return Pose(header=header(i), child_frame_id="marker/3",
                transform=Transform(translation=(0.1 * np.sin(angle), 0.05, 1.0 + 0.1 * np.cos(angle)),
                                    rotation=(0.0, float(np.sin(angle / 2)), 0.0, float(np.cos(angle / 2)))))


def markers(i: int) -> Message:
    corners = (np.array([[0, 0], [40, 0], [40, 40], [0, 40]], np.float32) + i % 50
               + np.arange(10, dtype=np.float32)[:, None, None] * 50)
    return MarkerDetections(header=header(i), dictionary="DICT_4X4_50", ids=np.arange(10, dtype=np.int32),
                            corners=corners, quality=np.ones(10, np.float32), side_m=np.full(10, 0.05, np.float32))


def keypoints(i: int) -> Message:
    points = np.random.default_rng(i).uniform(0, WIDTH, (500, 2)).astype(np.float32)
    ones = np.ones(500, np.float32)
    return Keypoints(header=header(i), descriptor_type="ORB", points=points, sizes=ones, angles=ones,
                     responses=ones, descriptors=np.zeros((500, 32), np.uint8))


def measure(folder: Path, name: str, make: Callable[[int], Message], count: int, **options: Any) -> dict[str, Any]:
    """Log ``WARMUP`` then ``count`` messages of ``make(i)`` into a fresh file; the variant's figures."""
    path = folder / f"{name}.rrd"
    messages = [make(i) for i in range(WARMUP + count)]
    view = ViewLog(open_recording(name, out=path), Scene(ViewOptions(**options)))
    for message in messages[:WARMUP]:
        view.log(message)
    calls = []
    started = time.perf_counter()
    for message in messages[WARMUP:]:
        before = time.perf_counter()
        view.log(message)
        calls.append(time.perf_counter() - before)
    view.close()
    amortized = (time.perf_counter() - started) / count * 1e3
    target = IMAGE_TARGET_MS if name.startswith("image") else RESULT_TARGET_MS
    p50, p99 = (float(v) * 1e3 for v in np.percentile(calls, [50, 99]))
    return {"bench": "viewer", "variant": name, "n": count, "options": options,
            "log_ms_p50": round(p50, 4), "log_ms_p99": round(p99, 4),
            "amortized_ms": round(amortized, 4), "bytes_per_msg": round(path.stat().st_size / (WARMUP + count)),
            "target": f"amortized <= {target} ms", "met": amortized <= target}


def bench_viewer() -> list[dict[str, Any]]:
    """Figures of raw and JPEG images, poses and detections (see the module docstring)."""
    images = image_maker()
    with tempfile.TemporaryDirectory(prefix="artrack-bench-viewer-") as folder:
        where = Path(folder)
        return [
            measure(where, "image_raw", images, IMAGES),
            measure(where, "image_jpeg", images, IMAGES, jpeg_quality=JPEG_QUALITY),
            measure(where, "pose", pose, RESULTS),
            measure(where, "markers", markers, RESULTS),
            measure(where, "keypoints", keypoints, RESULTS),
        ]


if __name__ == "__main__":
    for line in bench_viewer():
        print(json.dumps(line), flush=True)
