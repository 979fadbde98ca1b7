"""Monocular SLAM in one process: ``SlamSystem.process`` takes frames, returns each one's pose.

It ties together the feature extraction (``features``), the tracker (``frontend``), the map
(``map``) and the local mapper (``mapping``): in a process of its own (``mapping="process"``, the
default, ``mapping_process``), on a thread (``"thread"``) or inline (``"inline"``: each keyframe
mapped before ``process`` returns; deterministic). Mapping apart, a keyframe decision that hangs on
the mapper being idle takes it as busy when it is (real time: tracking waits only after a keyframe
made on a nearly lost frame, ``frontend.THIN_MAP_WAIT_S``), or with ``wait_for_mapping`` each new
keyframe is mapped before the next frame is tracked (``frontend``): a run fed every frame then gives
inline mapping's poses, whatever the load.
A map saved by an earlier run (``map.file``) can be given at the start: the system relocalises
in it first (``relocalisation``), then tracks it; with ``localisation_only`` the map stays fixed (no
keyframes, points or bundle adjustment), otherwise mapping carries on from it.
A map of its own that is lost while it has at most ``restart_keyframes`` keyframes is given up: a new
map is started from the lost frame on, placed and scaled where the camera's last motion carries it
(``frontend.Anchor``), and the frames tracked in the map given up keep their final poses in the
trajectory. A young map lost is a start that went wrong, or a camera moving on from what little it
mapped; waiting to relocalise in it would leave every frame after it untracked.
Frames: the world is the first keyframe's camera frame (OpenCV camera frame), in the map's
arbitrary monocular units; ``T_world_camera`` (4, 4) maps the frame's camera frame into it.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass

import numpy as np

from protocol.tracking_state import TrackingState
from services.geometry.camera import CameraModel
from services.geometry.se3 import invert
from services.slam.calibration_check import FocalCheck
from services.slam.features import FeatureExtractor
from services.slam.frontend import Tracked, Tracker
from services.slam.map.database import MapDatabase
from services.slam.map.file import MapFileError, load_map, save_map
from services.slam.mapping import LocalMapper, Mapper
from services.slam.mapping_process import MappingProcess
from services.slam.settings import SlamSettings
from services.slam.timing import stage_timer

__all__ = ["FrameResult", "MAPPING_MODES", "MapFileError", "SlamSettings", "SlamSystem"]

logger = logging.getLogger(__name__)

STEP_BACK_S = 1.0
"""A frame stamped no later than the previous one, and at most this many seconds before it, is out of
order (skipped); one stamped further back is a jump in the sequence, tracked (or relocalised) as usual."""
MAPPING_MODES = ("process", "thread", "inline")
"""Where local mapping runs (``SlamSystem``'s ``mapping``)."""


@dataclass(frozen=True)
class FrameResult:
    """One frame's outcome.

    ``state``; ``reason`` ("" when tracking, else why not: ``new_reference``, ``low_parallax``,
    ``planar_wait``, ``pose_uncertain``, ``too_few_matches``, ``too_few_points``, ``few_in_front``, ``no_texture``,
    ``bad_image``, ``out_of_order``, ``new_map`` on the frame that gives up a young map lost and starts
    another, and while relocalising ``no_candidates``, ``not_confirmed``; a
    tracked frame's is ``calibration_suspect`` once the camera matrix was found not to fit the map,
    ``calibration_check``); ``T_world_camera`` (4, 4) or None; ``tracked`` map points matched and kept;
    ``reprojection_rms_px`` of those (NaN without a pose); ``keyframe_id`` when this frame became a
    keyframe; ``timings_ms`` per stage (``map_sync``: bringing in the mapping process's changes,
    ``keypoints``, ``match``, ``pose``, ``local_map``, ``keyframe``, ``mapping_wait`` when the keyframe decision
    waited for the mapper (``wait_for_mapping``; included in ``keyframe``), ``initial_map`` on the frame that
    starts the map, ``mapping`` when a keyframe was mapped inline (included in ``keyframe``),
    ``relocalise_candidates`` and ``relocalise_pose`` on a frame after a lost one, ``calibration_check``
    on the frame that first has the mapper's check of the camera matrix (made after the map's
    ``CHECK_KEYFRAMES``-th keyframe, in the mapper's process or thread: the milliseconds it took there, not
    part of this frame's ``total`` unless mapping runs inline), ``total``)."""

    state: TrackingState
    reason: str
    T_world_camera: np.ndarray | None
    tracked: int
    reprojection_rms_px: float
    keyframe_id: int | None
    timings_ms: dict[str, float]


def _loaded_map(path: str | os.PathLike[str], camera: CameraModel, settings: SlamSettings) -> MapDatabase:
    """The map file's map, refused (``MapFileError``) without keyframes or made with another ORB pyramid."""
    slam_map = load_map(path, camera)
    if (slam_map.levels, slam_map.scale_factor) != (settings.levels, settings.scale_factor):
        raise MapFileError(path, f"made with a pyramid of {slam_map.levels} levels x {slam_map.scale_factor}, "
                                 f"these settings use {settings.levels} x {settings.scale_factor}")
    if not slam_map.keyframes:
        raise MapFileError(path, "holds no keyframes")
    return slam_map


def _check_camera(camera: CameraModel) -> None:
    """ValueError (one line) for a camera matrix SLAM cannot work with: focal lengths not finite and
    positive, or a principal point outside the image."""
    fx, fy, cx, cy = (float(v) for v in np.asarray(camera.K, np.float64)[[0, 1, 0, 1], [0, 1, 2, 2]])
    if not (np.isfinite([fx, fy, cx, cy]).all() and fx > 0 and fy > 0 and 0 <= cx < camera.width
            and 0 <= cy < camera.height):
        raise ValueError(f"camera {camera.name}: fx {fx}, fy {fy} must be positive and the principal point "
                         f"({cx}, {cy}) within the {camera.width}x{camera.height} image")


class SlamSystem:
    """Tracks one calibrated ``camera``'s frames while mapping; ``mapping``: one of ``MAPPING_MODES``
    (ValueError for another).

    ``map_path``: a map file to start from (``map.file.load_map``; ``MapFileError`` when it does not
    fit this camera or these settings' pyramid; ValueError for a camera matrix without positive focal
    lengths or with its principal point outside the image). ``localisation_only``: never change the map.
    ``save_path``: where ``close`` saves the map (None: not saved). ``wait_for_mapping``: each new
    keyframe is mapped before the next frame is tracked (for runs fed every frame, whose frames may wait:
    inline mapping's poses, whatever the load; off: real time, the decision takes a busy mapper as busy)."""

    def __init__(self, camera: CameraModel, settings: SlamSettings | None = None, *, mapping: str = "process",
                 map_path: str | os.PathLike[str] | None = None, localisation_only: bool = False,
                 save_path: str | os.PathLike[str] | None = None, wait_for_mapping: bool = False):
        if mapping not in MAPPING_MODES:
            raise ValueError(f"mapping {mapping!r}: one of {', '.join(MAPPING_MODES)}")
        _check_camera(camera)
        self.camera = camera
        self.settings = settings or SlamSettings()
        s = self.settings
        if localisation_only and map_path is None:
            raise ValueError("localisation_only needs a map to localise in (map_path)")
        self.map = MapDatabase(s.scale_factor, s.levels) if map_path is None else _loaded_map(map_path, camera, s)
        self.localisation_only = localisation_only
        self.save_path = save_path
        self.mapping = mapping
        self.wait_for_mapping = wait_for_mapping
        self._own_map = map_path is None
        self._extractor = FeatureExtractor(camera, s.max_keypoints, s.levels, s.scale_factor, s.fast_threshold)
        self._mapper = self._new_mapper()
        self._tracker = Tracker(camera, s, self.map, self._mapper, localisation_only, wait_for_mapping)
        self._tracked: list[tuple[int, int, np.ndarray]] = []
        """Every tracked frame's ``(stamp_ns, reference keyframe id, (4, 4) T_camera_keyframe)``."""
        self._given_up: list[tuple[int, np.ndarray]] = []
        """``(stamp_ns, (4, 4) T_world_camera)``: the final poses of the frames tracked in maps given up."""
        self.maps_given_up = 0
        self._last_stamp: int | None = None
        self._calibration: str | None = None
        """"ok", "calibration_suspect", or None before the check."""

    def process(self, stamp_ns: int, image: np.ndarray) -> FrameResult:
        """Track one frame: grey (H, W) or BGR(A) (H, W, 3|4), uint8 or uint16, of the camera's size.
        Never raises on a bad frame: it comes back lost (or initialising) with the reason. A frame of the
        wrong size or type (``bad_image``) or out of order (``out_of_order``, see ``STEP_BACK_S``) is
        skipped: the tracker does not see it, the next frame goes on from the last one."""
        timings: dict[str, float] = {}
        with stage_timer(timings, "total"):
            with stage_timer(timings, "map_sync"):
                self._mapper.sync()
            if not self._fits(image):
                tracked = Tracked(self._tracker_state(), "bad_image")
            elif self._out_of_order(stamp_ns):
                tracked = Tracked(self._tracker_state(), "out_of_order")
            else:
                self._last_stamp = stamp_ns
                with stage_timer(timings, "keypoints"):
                    features = self._extractor.extract(image)
                tracked = self._tracker.track(stamp_ns, features, timings)
                if tracked.state is TrackingState.LOST and self._gives_up():
                    self._new_map()
                    tracked = Tracked(self._tracker.track(stamp_ns, features, timings).state, "new_map")
            if tracked.keyframe_id is not None and self.mapping == "inline" and "initial_map" not in timings:
                timings["mapping"] = sum(self._mapper.history[-1].stages.values())
            if self._calibration is None and (check := self._mapper.focal_check) is not None:
                self._report_calibration(check)
                timings["calibration_check"] = check.took_ms
        if tracked.T_camera_world is not None:
            self._remember(stamp_ns, tracked.T_camera_world, tracked.keyframe_id)
        pose = None if tracked.T_camera_world is None else invert(tracked.T_camera_world)
        reason = tracked.reason
        if tracked.state is TrackingState.TRACKING and self._calibration == "calibration_suspect":
            reason = self._calibration
        return FrameResult(tracked.state, reason, pose, tracked.tracked, tracked.rms_px, tracked.keyframe_id,
                           timings)

    def _new_mapper(self) -> Mapper:
        """The mapper of ``self.map``: in a process of its own, on a thread or inline (``mapping``)."""
        s, size = self.settings, (self.camera.width, self.camera.height)
        if self.mapping == "process" and not self.localisation_only:
            return MappingProcess(self.map, self.camera.K, size, s)
        return LocalMapper(self.map, self.camera.K, size, s,
                           threaded=self.mapping == "thread" and not self.localisation_only)

    def _gives_up(self) -> bool:
        """Whether the map, just lost, is young enough to give up (a map of its own, not localising)."""
        return (self._own_map and not self.localisation_only
                and 0 < len(self.map.keyframes) <= self.settings.restart_keyframes)

    def _new_map(self) -> None:
        """Give the lost map up for a new one placed where the camera's motion carries it (module docstring):
        its mapper stopped, its frames' final poses kept for ``trajectory``."""
        anchor = self._tracker.anchor()
        self._mapper.close()
        self._given_up = self.trajectory()
        self._tracked = []
        logger.info("camera %s: the map was lost with %d keyframes; a new map starts from this frame, placed where "
                    "the camera's motion carries it", self.camera.name, len(self.map.keyframes))
        s = self.settings
        revision = self.map.revision
        self.map = MapDatabase(s.scale_factor, s.levels)
        self.map.revision = revision + 1
        self._mapper = self._new_mapper()
        self._tracker = Tracker(self.camera, s, self.map, self._mapper, False, self.wait_for_mapping, anchor)
        self.maps_given_up += 1

    def _remember(self, stamp_ns: int, T_camera_world: np.ndarray, keyframe_id: int | None) -> None:
        """Keep a tracked frame's pose relative to its reference keyframe (itself when it became one)."""
        if keyframe_id is not None:
            self._tracked.append((stamp_ns, keyframe_id, np.eye(4)))
            return
        with self.map.lock:
            keyframe = self.map.keyframes.get(self._tracker.reference_keyframe)
            if keyframe is not None:
                self._tracked.append((stamp_ns, keyframe.id, T_camera_world @ invert(keyframe.T_camera_world)))

    def _report_calibration(self, check: FocalCheck) -> None:
        self._calibration = "calibration_suspect" if check.suspect else "ok"
        logger.log(logging.WARNING if check.suspect else logging.INFO, "camera %s: %s%s", self.camera.name,
                   check.line(), ": the calibration looks wrong, poses are suspect" if check.suspect else "")

    def _fits(self, image: np.ndarray) -> bool:
        size = (self.camera.height, self.camera.width)
        good = (isinstance(image, np.ndarray) and image.dtype in (np.uint8, np.uint16) and image.shape[:2] == size
                and (image.ndim == 2 or (image.ndim == 3 and image.shape[2] in (3, 4))))
        if not good:
            logger.warning("frame skipped: expected (%d, %d[, 3|4]) uint8/uint16, got %s %s", *size,
                           getattr(image, "shape", None), getattr(image, "dtype", None))
        return good

    def _out_of_order(self, stamp_ns: int) -> bool:
        back_s = np.inf if self._last_stamp is None else (self._last_stamp - stamp_ns) * 1e-9
        skipped = 0 <= back_s <= STEP_BACK_S
        if skipped:
            logger.warning("frame skipped: stamped %.3f s before the previous frame (out of order)", back_s)
        return skipped

    def _tracker_state(self) -> TrackingState:
        return TrackingState.LOST if self.map.keyframes else TrackingState.INITIALISING

    def keyframe_poses(self) -> list[tuple[int, int, np.ndarray]]:
        """(keyframe id, stamp_ns, (4, 4) T_world_camera) of every keyframe, oldest first."""
        with self.map.lock:
            return [(k.id, k.stamp_ns, invert(k.T_camera_world)) for k in self.map.keyframes.values()]

    def trajectory(self) -> list[tuple[int, np.ndarray]]:
        """``(stamp_ns, (4, 4) T_world_camera)`` of every frame tracked so far, oldest first: each frame's
        pose relative to its reference keyframe (as tracked) composed with that keyframe's current,
        bundle-adjusted pose (the frames of maps given up: as their map left them). Frames never tracked
        are left out. Keyframes are never removed from a map, so every tracked frame keeps its reference."""
        tracked = list(self._tracked)
        with self.map.lock:
            keyframes = {k.id: k.T_camera_world.copy() for k in self.map.keyframes.values()}
        return [*self._given_up, *((stamp_ns, invert(T_camera_keyframe @ keyframes[keyframe_id]))
                                   for stamp_ns, keyframe_id, T_camera_keyframe in tracked if keyframe_id in keyframes)]

    def map_points(self) -> tuple[np.ndarray, np.ndarray]:
        """``(ids (N,) int64, positions (N, 3) world)`` of every map point."""
        with self.map.lock:
            ids = self.map.point_ids()
            return ids, self.map.positions(ids)

    @property
    def map_revision(self) -> int:
        """Grows whenever keyframes or points change."""
        return self.map.revision

    def save_map(self, path: str | os.PathLike[str]) -> None:
        """Write the map to ``path`` (``map.file`` format): a snapshot taken under the map's lock."""
        save_map(self.map, self.camera, path)

    def close(self) -> None:
        """Stop the mapping thread or process (after the keyframes it was given, their changes brought
        in), then save the map to ``save_path`` when one was given."""
        self._mapper.close()
        if self.save_path is not None:
            save_map(self.map, self.camera, self.save_path)
