"""What the marker and features nodes do per frame beyond their method, in this process.

Each tracker first runs its method over the frames once, as its node does, and keeps the results:

* ``marker_pose``: the ``markers`` scene (640x480, ``FRAMES`` frames), each frame's markers detected
  (``DetectorSettings(marker_length=MARKER_LENGTH)``, the calibration known) and their poses estimated;
* ``features``: the ``planar_target`` scene (640x480, ``FRAMES`` frames), its own target tracked
  frame after frame (``track_targets``, the features node's default options).

Then, ``ROUNDS`` times over all the frames, the node's own per-frame work on those results, timed per
frame: the camera model of the frame's CameraInfo (a capture node sends one with every frame, the
same each time; both nodes make theirs with ``CameraModels``), then for ``marker_pose`` the detections
message (``as_message``) and the node's publishing path of the estimate (``_estimate`` handed the
stored estimate: reports, the pose messages, the lost targets'), for ``features`` the pose message
of each target (``as_pose``) and their publishing. Publishers keep
nothing, so the bus's own cost (encoding, sending) is left out: the figures are the node's messages
and loops alone. Per round the median over the frames; the line gives the median over rounds
(``node_work_us``, and per pose), with the method's own p50 per frame for scale.

``python -m tests.bench.node_work`` prints one line per node (about 20 s).
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from protocol.keys import Keys
from protocol.message import Header, Message
from services.convert import CameraModels, camera_info
from services.detection.markers.node import as_message
from services.detection.markers.settings import DetectorSettings
from services.estimation.markers import node as marker_node
from services.estimation.markers.pose import FrameEstimate, MarkerPoseEstimator
from services.estimation.targets.node import Params, as_pose, load_targets, make_trackers
from services.estimation.targets.tracking import track_targets
from services.synthetic import make_scene
from tests.bench.features_bus import _frames, _target

FRAMES = 300
ROUNDS = 7
MARKER_LENGTH = 0.05
DICTIONARY = "DICT_4X4_50"
CAMERA = "cam0"


class _Dropped:
    """A publisher that drops what it is given: the bus's share of a frame is not the node's."""

    def put(self, message: Message) -> None:
        pass

    def matched(self) -> bool:
        return False


class _Stub:
    """The parts of a ``Node`` a tracker's per-frame helpers use."""

    keys = Keys()

    def publisher(self, key: str, cls: type[Message], role: Any = None) -> _Dropped:
        return _Dropped()

    def report(self, *args: Any) -> None:
        pass


class _Replay:
    """Hands out stored estimates in turn, where the node asks its estimator for one."""

    def __init__(self, estimates: list[FrameEstimate]):
        self._estimates = iter(estimates)

    def estimate(self, *args: Any) -> FrameEstimate:
        return next(self._estimates)


def _header(seq: int) -> Header:
    return Header(stamp_ns=1_000_000_000 + seq * 16_666_667, frame_id=CAMERA, seq=seq)


def _rounds(frame_work: Callable[[], Callable[[int], None]]) -> float:
    """Median over ``ROUNDS`` of the per-frame median (us) of ``frame_work()(seq)`` over the frames."""
    medians = []
    for _ in range(ROUNDS):
        work = frame_work()
        times = []
        for seq in range(FRAMES):
            started = time.perf_counter()
            work(seq)
            times.append(time.perf_counter() - started)
        medians.append(float(np.median(times)) * 1e6)
    return float(np.median(medians))


def marker_pose() -> dict[str, Any]:
    scene = make_scene("markers")
    camera = scene.cameras[0]
    detector, estimator = DetectorSettings(marker_length=MARKER_LENGTH).detector(), MarkerPoseEstimator()
    found, estimates, method = [], [], []
    for seq in range(FRAMES):
        image = scene.render(seq).images[camera.name]
        started = time.perf_counter()
        markers = detector.detect(image, camera.K, camera.dist)
        estimates.append(estimator.estimate(markers.ids, markers.corners, markers.side_m, camera.K, camera.dist))
        method.append(time.perf_counter() - started)
        found.append(markers)
    headers = [_header(seq) for seq in range(FRAMES)]
    infos = [camera_info(header, camera) for header in headers]

    def frame_work() -> Callable[[int], None]:
        node, replay, models = _Stub(), _Replay(estimates), CameraModels()
        poses = marker_node.PosePublishers(node, CAMERA)  # type: ignore[arg-type]

        def work(seq: int) -> None:
            models(infos[seq])
            detections = as_message(headers[seq], DICTIONARY, found[seq])
            marker_node._estimate(node, detections, camera, replay, poses)  # type: ignore[arg-type]
        return work

    return _line("marker_pose", method, sum(len(e.poses) for e in estimates), _rounds(frame_work))


def features() -> dict[str, Any]:
    frames, camera = _frames(FRAMES)
    params = Params(**_target())
    trackers = make_trackers(params, load_targets(params))
    results, method = [], []
    for seq, image in enumerate(frames):
        started = time.perf_counter()
        results.append(track_targets(trackers, image, camera.K, camera.dist, _header(seq).stamp_ns))
        method.append(time.perf_counter() - started)
    headers = [_header(seq) for seq in range(FRAMES)]
    infos = [camera_info(header, camera) for header in headers]

    def frame_work() -> Callable[[int], None]:
        poses, models = marker_node.PosePublishers(_Stub(), CAMERA), CameraModels()  # type: ignore[arg-type]

        def work(seq: int) -> None:
            models(infos[seq])
            poses.publish([as_pose(headers[seq], found) for found in results[seq]])
        return work

    return _line("features", method, sum(map(len, results)), _rounds(frame_work))


def _line(node: str, method_s: list[float], poses: int, node_work_us: float) -> dict[str, Any]:
    per_frame = poses / FRAMES
    return {"bench": "node_work", "node": node, "width": 640, "height": 480, "frames": FRAMES, "rounds": ROUNDS,
            "method_p50_ms": round(float(np.median(method_s)) * 1e3, 3), "poses_per_frame": round(per_frame, 2),
            "node_work_us": round(node_work_us, 1), "per_pose_us": round(node_work_us / max(per_frame, 1e-9), 2)}


def bench_node_work() -> list[dict[str, Any]]:
    return [marker_pose(), features()]


if __name__ == "__main__":
    for line in bench_node_work():
        print(json.dumps(line), flush=True)
