"""Monocular SLAM in one process: ``SlamSystem.process`` takes frames, returns each one's pose.

It ties together the feature extraction (``features``), the tracker (``frontend``), the map
(``map``) and the local mapper (``mapping``, on its own thread unless ``mapping_thread=False``).
Frames: the world is the first keyframe's camera frame (OpenCV camera frame), in the map's
arbitrary monocular units; ``T_world_camera`` (4, 4) maps the frame's camera frame into it.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from services.geometry.camera import CameraModel
from services.geometry.se3 import invert
from services.slam.features import FeatureExtractor
from services.slam.frontend import SlamState, Tracked, Tracker
from services.slam.map import SlamMap
from services.slam.mapping import LocalMapper
from services.slam.settings import SlamSettings
from services.slam.timing import stage_timer

__all__ = ["FrameResult", "SlamSettings", "SlamState", "SlamSystem"]

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class FrameResult:
    """One frame's outcome.

    ``state``; ``reason`` ("" when tracking, else why not: ``new_reference``, ``low_parallax``,
    ``planar_wait``, ``too_few_matches``, ``too_few_points``, ``few_in_front``, ``no_texture``,
    ``bad_image``); ``T_world_camera`` (4, 4) or None; ``tracked`` map points matched and kept;
    ``reprojection_rms_px`` of those (NaN without a pose); ``keyframe_id`` when this frame became a
    keyframe; ``timings_ms`` per stage (``keypoints``, ``match``, ``pose``, ``local_map``,
    ``keyframe``, ``initial_map`` on the frame that starts the map, ``mapping`` when a keyframe was
    mapped inline (included in ``keyframe``), ``total``)."""

    state: SlamState
    reason: str
    T_world_camera: np.ndarray | None
    tracked: int
    reprojection_rms_px: float
    keyframe_id: int | None
    timings_ms: dict[str, float]


class SlamSystem:
    """Tracks one calibrated ``camera``'s frames while mapping; ``mapping_thread=False`` maps inline
    (each keyframe is processed before ``process`` returns: deterministic)."""

    def __init__(self, camera: CameraModel, settings: SlamSettings | None = None, *, mapping_thread: bool = True):
        self.camera = camera
        self.settings = settings or SlamSettings()
        s = self.settings
        self.map = SlamMap(s.scale_factor, s.levels)
        self._extractor = FeatureExtractor(camera, s.max_keypoints, s.levels, s.scale_factor, s.fast_threshold)
        self._mapper = LocalMapper(self.map, camera.K, (camera.width, camera.height), s, threaded=mapping_thread)
        self._tracker = Tracker(camera, s, self.map, self._mapper)
        self._threaded = mapping_thread

    def process(self, stamp_ns: int, image: np.ndarray) -> FrameResult:
        """Track one frame: grey (H, W) or BGR(A) (H, W, 3|4), uint8 or uint16, of the camera's size.
        Never raises on a bad frame: it comes back lost (or initialising) with the reason."""
        timings: dict[str, float] = {}
        with stage_timer(timings, "total"):
            if not self._fits(image):
                tracked = Tracked(self._tracker_state(), "bad_image")
            else:
                with stage_timer(timings, "keypoints"):
                    features = self._extractor.extract(image)
                tracked = self._tracker.track(stamp_ns, features, timings)
            if tracked.keyframe_id is not None and not self._threaded and "initial_map" not in timings:
                timings["mapping"] = sum(self._mapper.timings_ms.values())
        pose = None if tracked.T_camera_world is None else invert(tracked.T_camera_world)
        return FrameResult(tracked.state, tracked.reason, pose, tracked.tracked, tracked.rms_px, tracked.keyframe_id,
                           timings)

    def _fits(self, image: np.ndarray) -> bool:
        size = (self.camera.height, self.camera.width)
        good = (isinstance(image, np.ndarray) and image.dtype in (np.uint8, np.uint16) and image.shape[:2] == size
                and (image.ndim == 2 or (image.ndim == 3 and image.shape[2] in (3, 4))))
        if not good:
            logger.warning("frame skipped: expected (%d, %d[, 3|4]) uint8/uint16, got %s %s", *size,
                           getattr(image, "shape", None), getattr(image, "dtype", None))
        return good

    def _tracker_state(self) -> SlamState:
        return SlamState.LOST if self.map.keyframes else SlamState.INITIALISING

    def keyframe_poses(self) -> list[tuple[int, int, np.ndarray]]:
        """(keyframe id, stamp_ns, (4, 4) T_world_camera) of every keyframe, oldest first."""
        with self.map.lock:
            return [(k.id, k.stamp_ns, invert(k.T_camera_world)) for k in self.map.keyframes.values()]

    def map_points(self) -> tuple[np.ndarray, np.ndarray]:
        """``(ids (N,) int64, positions (N, 3) world)`` of every map point."""
        with self.map.lock:
            ids = self.map.point_ids()
            positions = np.array([self.map.points[i].position for i in ids.tolist()], np.float64).reshape(-1, 3)
        return ids, positions

    @property
    def map_revision(self) -> int:
        """Grows whenever keyframes or points change."""
        return self.map.revision

    def close(self) -> None:
        """Stop the mapping thread (after the keyframes it was given)."""
        self._mapper.close()
