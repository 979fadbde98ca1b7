"""Tracking: the camera pose of every frame against the map, and the decision to make it a keyframe.

Until a map exists, a reference frame is matched by descriptor with each new frame (each keypoint
with the keypoints within a window around its pixel on a neighbouring level) and handed to
``services.slam.initialisation.initialise``; the first accepted pair makes the map's first two
keyframes and points (scaled so that their median depth is 1). The reference frame is replaced
when it is ``reference_max_age`` frames old, or when it shares too few matches with the new one.

A pair needs the full parallax bound (``InitialisationSettings.min_parallax_deg``) until the new
frame is ``init_late_frames`` after the reference, and ``init_late_parallax_deg`` from then on: the
parallax grows about as the baseline, so waiting one more frame doubles it at the first frame and
adds a quarter at the fourth. A map started under the full bound is young: its structure, from a
short baseline, is settled by keyframes made each time the camera is as far from the last keyframe
as the first two keyframes are apart (with the mapper idle), until it has ``young_map_keyframes``.

Then, for each frame (as ORB-SLAM does):

1. Predict the pose with a constant-velocity model and search the last frame's points by
   projection around it (``projection``), with a wider window when too few are found; refine the
   pose on those matches (robust, pose only).
2. When that fails (too few matches or inliers: after a gap, a jerk, or frames ~1 s apart), match
   the frame's descriptors with the points of the local map and solve PnP with RANSAC
   (``relocalisation.solve_pnp``), then refine. After a lost frame, or on a map given at the start
   (loaded from a file: the tracker starts lost), ``relocalisation.Relocaliser`` searches the whole map.
3. Search the local map (the points of the keyframes observing the matched points and of their
   best covisible keyframes) by projection with the refined pose, and refine again on all matches.
4. When all of that fails within ``BRIDGE_MAX_S`` of the last tracked frame (frames dropped, or a
   stretch of forward motion the map does not reach), bridge the frame from the last tracked one
   (``bridging``): the pair's two-view model and points in the map's frame and scale, the last frame
   made a keyframe if it was not one, the new frame a keyframe with the pair's points.

With ``localisation_only`` the map stays as it is: frames are tracked, no keyframe is made.

A young map that is lost (``services.slam.system`` gives it up) leaves an ``Anchor``: the last tracked
frame's pose and the camera's motion then. The next map's first keyframe is placed where that motion
carries the camera by the time of its reference frame, and its first pair is scaled to the distance the
camera covers at that speed between the pair's frames, so the new map goes on in the world and scale of
the one given up (forward motion seldom comes back to the places a lost map holds).

The keyframe decision (``mapping.keyframe_decision``) may hang on whether the mapper is idle, which
depends on the machine's load when mapping runs apart. With ``wait_for_mapping`` the tracker waits
for the mapper instead (at most ``MAPPING_WAIT_S``, a warning when that passes): after each keyframe
it makes, until that keyframe is mapped and its changes are in, so each frame is tracked against the
map inline mapping would give it and a run fed every frame gives the same poses on a busy machine as
on an idle one. Without it the tracker waits only after a keyframe made on a nearly lost frame (under
twice ``min_tracked``), at most ``THIN_MAP_WAIT_S``: a camera moving forward leaves its points behind
within a few frames, and frames tracked before that keyframe's points are in would be lost.

Frames: poses are ``T_camera_world`` (4, 4), world = the first keyframe's camera frame (of the first map:
a map placed by an anchor keeps its world).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np

from protocol.tracking_state import TrackingState
from services.geometry.camera import CameraModel
from services.geometry.rotation import matrix_from_rotvec, rotvec_from_matrix
from services.geometry.se3 import invert, make_transform, transform_points
from services.slam.bridging import Bridge, bridge_pair
from services.slam.features import FrameFeatures
from services.slam.initialisation import InitialisationSettings, InitialisationStatus, initialise
from services.slam.map.covisibility import CovisibilityGraph
from services.slam.map.database import MapDatabase
from services.slam.map.keyframe import Keyframe
from services.slam.map.map_point import PointArrays
from services.slam.mapping import KeyframeDecision, Mapper, keyframe_decision
from services.slam.matching import match_descriptors, rotation_consistent, search_by_projection
from services.slam.optimisation import refine_pose, reprojection_errors
from services.slam.projection import project_points, search_projected
from services.slam.relocalisation import Relocaliser, solve_pnp
from services.slam.settings import SlamSettings
from services.slam.timing import stage_timer

__all__ = ["MAPPING_WAIT_S", "Anchor", "Tracked", "Tracker", "extrapolated"]

logger = logging.getLogger(__name__)

THIN_MAP_WAIT_S = 2.0
"""The longest a real-time tracker waits for the mapper after a keyframe made because the frame was
nearly lost (under twice ``min_tracked``): the next frames would find no map to track against (a camera
moving forward leaves its points behind within a few frames), so they are better late than lost."""
BRIDGE_MAX_S = 1.0
"""The longest time since the last tracked frame over which a frame the map no longer reaches is bridged
from it (``bridging``): the constant-velocity model's distance, and the overlap of the two frames, hold
for about that long."""
BRIDGE_WINDOW_PX = 200.0
"""How far a keypoint of the last tracked frame is searched for in the frame bridged from it, px: a camera
moving forward spreads the image out from the centre, fastest at the image's edges."""
SPEED_KEYFRAMES = 5
"""Keyframes over which the camera's speed is measured, for the distance a bridge spans."""
SPEED_AGREEMENT = 1.25
"""The most the last frame's step and the keyframes' speed may differ (as a ratio) for a steady speed."""
MAPPING_WAIT_S = 60.0
"""The longest a keyframe decision waits for the mapper (``Tracker``'s ``wait_for_mapping``): far beyond a
keyframe's mapping on a loaded machine; past it the frame is decided with the mapper busy."""


@dataclass(frozen=True)
class Tracked:
    """One frame's outcome: ``state`` (``initialising``: no map yet, ``tracking`` the map, or ``lost``);
    ``reason`` ("" when tracking); ``T_camera_world`` (4, 4) or None; ``tracked`` map points kept as
    inliers; ``rms_px`` their reprojection RMS (NaN without a pose); ``keyframe_id`` when the frame
    became a keyframe."""

    state: TrackingState
    reason: str
    T_camera_world: np.ndarray | None = None
    tracked: int = 0
    rms_px: float = float("nan")
    keyframe_id: int | None = None


def extrapolated(T_camera_world: np.ndarray, velocity: tuple[np.ndarray, float], seconds: float) -> np.ndarray:
    """(4, 4) ``T_camera_world`` carried ``seconds`` on by the constant ``velocity`` ``(T_current_previous
    (4, 4), its time step s)``: the step's rotation vector and translation scaled by ``seconds`` over the step."""
    delta, dt = velocity
    ratio = seconds / dt
    rotation = matrix_from_rotvec(rotvec_from_matrix(delta[:3, :3]) * ratio)
    return make_transform(rotation, delta[:3, 3] * ratio) @ T_camera_world


@dataclass(frozen=True)
class Anchor:
    """Where a map given up leaves the camera: the last tracked frame's ``T_camera_world`` (4, 4) and
    ``stamp_ns``, its ``velocity`` ``(T_current_previous (4, 4), time step s)`` (None when unknown) and
    ``speed`` (world units per second, NaN when unknown)."""

    T_camera_world: np.ndarray
    stamp_ns: int
    velocity: tuple[np.ndarray, float] | None
    speed: float

    def place(self, first_ns: int, second_ns: int, baseline: float) -> tuple[np.ndarray, float] | None:
        """``(T_camera_world (4, 4) of the pair's first frame, scale of its two-view model)`` for a pair stamped
        ``first_ns`` and ``second_ns`` whose model puts its frames ``baseline`` apart: the first frame where
        the velocity carries the last one, the pair as far apart as the speed takes the camera. None without a
        known speed, or when the pair spans no time."""
        span_s = (second_ns - first_ns) * 1e-9
        if not (np.isfinite(self.speed) and self.speed > 0 and span_s > 0 and baseline > 0):
            return None
        T = self.T_camera_world if self.velocity is None else extrapolated(
            self.T_camera_world, self.velocity, (first_ns - self.stamp_ns) * 1e-9)
        return T, self.speed * span_s / baseline


@dataclass
class _Frame:
    """A frame the tracker remembers: ``index`` counts frames; ``point_ids`` (N,) int64 per keypoint."""

    index: int
    stamp_ns: int
    features: FrameFeatures
    T_camera_world: np.ndarray
    point_ids: np.ndarray


class Tracker:
    """Tracks ``camera``'s frames against ``slam_map``, handing new keyframes to ``mapper`` (none with
    ``localisation_only``). ``wait_for_mapping``: a keyframe decision that hangs on the mapper being
    idle waits for it (``mapping.Mapper.wait_idle``) instead of taking it as busy. ``anchor``: where the
    map to be started goes (a map given up before it), None for a map of its own world and scale."""

    def __init__(self, camera: CameraModel, settings: SlamSettings, slam_map: MapDatabase, mapper: Mapper,
                 localisation_only: bool = False, wait_for_mapping: bool = False, anchor: Anchor | None = None):
        self.K = np.asarray(camera.K, np.float64)
        self.size = (camera.width, camera.height)
        self.settings = settings
        self.map = slam_map
        self.covisibility = CovisibilityGraph(slam_map)
        self.mapper = mapper
        self._index = -1
        self._reference: _Frame | None = None
        self._planes: np.ndarray | None = None
        """The plane normals of the first pair with the reference frame that a plane left ambiguous."""
        self._last: _Frame | None = None
        self._velocity: tuple[np.ndarray, float] | None = None
        """The last frame-to-frame motion ``T_current_previous`` and its time step, s."""
        self._lost = int(bool(slam_map.keyframes))
        self._relocaliser = Relocaliser(slam_map, self.K, self.size, settings)
        self.localisation_only = localisation_only
        self.wait_for_mapping = wait_for_mapping
        self._reference_keyframe = -1
        self._last_keyframe_stamp = 0
        self._last_keyframe_id = -1
        self._full_bound = InitialisationSettings()
        self._late_bound = self._full_bound.model_copy(update={"min_parallax_deg": settings.init_late_parallax_deg})
        self._young_baseline: float | None = None
        """The distance between the first two keyframes' centres (world units) while the map is young, else None."""
        self._anchor = anchor

    @property
    def reference_keyframe(self) -> int:
        """The id of the keyframe sharing most points with the last tracked frame (the frame itself when
        it became a keyframe); -1 before the map exists."""
        return self._reference_keyframe

    def anchor(self) -> Anchor | None:
        """Where the camera was when last tracked, and its motion then, for a map to start in this one's world
        (None before a frame was tracked). The speed is the last step's, else the keyframes' path over its
        time."""
        last = self._last
        if last is None:
            return None
        if self._velocity is not None:
            delta, dt = self._velocity
            speed = float(np.linalg.norm(delta[:3, 3])) / dt
        else:
            with self.map.lock:
                keyframes = sorted(self.map.keyframes.values(), key=lambda keyframe: keyframe.stamp_ns)
            span_s = (keyframes[-1].stamp_ns - keyframes[0].stamp_ns) * 1e-9 if keyframes else 0.0
            centres = np.array([keyframe.centre for keyframe in keyframes]).reshape(-1, 3)
            path = float(np.sum(np.linalg.norm(np.diff(centres, axis=0), axis=1)))
            speed = path / span_s if span_s > 0 else float("nan")
        return Anchor(last.T_camera_world.copy(), last.stamp_ns, self._velocity, speed)

    def track(self, stamp_ns: int, features: FrameFeatures, timings: dict[str, float]) -> Tracked:
        """The outcome of one frame's ``features``; adds the stages' milliseconds to ``timings``."""
        self._index += 1
        started = bool(self.map.keyframes) and (self._last is not None or self._lost > 0)
        if len(features) < self.settings.min_tracked:
            self._lost += int(bool(started))
            return Tracked(TrackingState.LOST if started else TrackingState.INITIALISING, "no_texture")
        if not started:
            return self._initialise(stamp_ns, features, timings)
        return self._track(stamp_ns, features, timings)

    def _initialise(self, stamp_ns: int, features: FrameFeatures, timings: dict[str, float]) -> Tracked:
        s = self.settings
        frame = _Frame(self._index, stamp_ns, features, np.eye(4), np.full(len(features), -1, np.int64))
        reference = self._reference
        if reference is None or self._index - reference.index > s.reference_max_age:
            self._new_reference(frame)
            return Tracked(TrackingState.INITIALISING, "new_reference")
        with stage_timer(timings, "match"):
            first = reference.features
            a, b = search_by_projection(first.pixels, np.full(len(first), s.init_window_px), first.levels,
                                        first.descriptors, features.pixels, features.levels, features.descriptors,
                                        np.ones(len(features), bool), s.match_max_distance, s.init_ratio)
            consistent = rotation_consistent(reference.features.angles[a], features.angles[b])
            a, b = a[consistent], b[consistent]
        late = self._index - reference.index >= s.init_late_frames
        with stage_timer(timings, "pose"):
            found = initialise(reference.features.pixels[a], features.pixels[b], self.K, np.zeros(5),
                               self._late_bound if late else self._full_bound, self._planes)
        if found.status is InitialisationStatus.PLANAR_WAIT and self._planes is None:
            self._planes = found.plane_normals
        if found.status is InitialisationStatus.TOO_FEW_MATCHES:
            self._new_reference(frame)
        if not found.initialised or found.T_second_first is None:
            return Tracked(TrackingState.INITIALISING, found.status.value)
        if int(found.inliers.sum()) < s.init_min_points:
            return Tracked(TrackingState.INITIALISING, "too_few_points")
        with stage_timer(timings, "initial_map"):
            keyframe_id = self._start_map(reference, frame, a[found.inliers], b[found.inliers],
                                          found.points[found.inliers], found.T_second_first)
        if keyframe_id is None:
            self._new_reference(frame)
            return Tracked(TrackingState.INITIALISING, "too_few_points")
        if found.parallax_deg < self._full_bound.min_parallax_deg:
            with self.map.lock:
                centres = [self.map.keyframes[k].centre for k in sorted(self.map.keyframes)]
            self._young_baseline = float(np.linalg.norm(centres[1] - centres[0]))
        last = self._last
        assert last is not None
        seen = np.flatnonzero(last.point_ids >= 0)
        points = self.map.arrays(last.point_ids[seen])
        seen = seen[np.isin(last.point_ids[seen], points.ids)]
        errors = reprojection_errors(self.K, last.T_camera_world, points.positions, features.pixels[seen])
        return Tracked(TrackingState.TRACKING, "", last.T_camera_world.copy(), len(seen),
                       float(np.sqrt(np.mean(errors**2))), keyframe_id)

    def _new_reference(self, frame: _Frame) -> None:
        """Pair the next frames with ``frame``, forgetting the planes of the last reference."""
        self._reference = frame
        self._planes = None

    def _start_map(self, reference: _Frame, frame: _Frame, a: np.ndarray, b: np.ndarray, points: np.ndarray,
                   T_second_first: np.ndarray) -> int | None:
        """The map's first two keyframes and points (``points`` (N, 3) in the first frame's camera frame; median
        depth scaled to 1, or placed and scaled by the anchor, then bundle adjusted); the second keyframe's id,
        or None (map cleared) when too few points survive."""
        scale, T_first = 1.0 / float(np.median(points[:, 2])), np.eye(4)
        placed = None if self._anchor is None else self._anchor.place(
            reference.stamp_ns, frame.stamp_ns, float(np.linalg.norm(T_second_first[:3, 3])))
        if placed is not None:
            T_first, scale = placed
        T = T_second_first.copy()
        T[:3, 3] *= scale
        first = self.map.add_keyframe(reference.stamp_ns, T_first, reference.features, reference.point_ids)
        second = self.map.add_keyframe(frame.stamp_ns, T @ T_first, frame.features, frame.point_ids)
        for point, i, j in zip(transform_points(invert(T_first), points * scale), a, b, strict=True):
            self.map.add_point(point, {first.id: int(i), second.id: int(j)})
        self.mapper.adjust_initial_map(first.id, second.id)
        if len(self.map.points) < self.settings.init_min_points:
            self.map.clear()
            return None
        frame.T_camera_world = second.T_camera_world.copy()
        frame.point_ids = second.point_ids.copy()
        self._last = frame
        self._anchor = None
        self._velocity = (T, (frame.stamp_ns - reference.stamp_ns) * 1e-9) if frame.stamp_ns > reference.stamp_ns \
            else None
        self._reference_keyframe = second.id
        self._last_keyframe_stamp = frame.stamp_ns
        self._last_keyframe_id = second.id
        return second.id

    def _track(self, stamp_ns: int, features: FrameFeatures, timings: dict[str, float]) -> Tracked:
        last = self._last
        point_ids = np.full(len(features), -1, np.int64)
        found = weak = None
        reason = "too_few_matches"
        if self._lost == 0 and last is not None:
            T, inliers = self._follow_motion(last, stamp_ns, features, point_ids, timings)
            if T is not None and inliers >= self.settings.min_motion_matches:
                with stage_timer(timings, "local_map"):
                    found = self._track_local_map(T, features, point_ids)
            elif T is not None:
                weak = T, point_ids.copy()
        if found is None:
            point_ids[:] = -1
            T, reason = self._relocate(last, features, point_ids, timings)
            if T is not None:
                with stage_timer(timings, "local_map"):
                    found = self._track_local_map(T, features, point_ids)
        if found is None and weak is not None:
            T, point_ids[:] = weak
            with stage_timer(timings, "local_map"):
                found = self._track_local_map(T, features, point_ids)
        if found is None and last is not None and self._may_bridge(last, stamp_ns):
            with stage_timer(timings, "bridge"):
                bridged = self._bridge(last, stamp_ns, features, timings)
            if bridged is not None:
                return bridged
        if found is None:
            self._lost += 1
            return Tracked(TrackingState.LOST, reason or "too_few_matches")
        T, rms = found
        tracked = int(np.count_nonzero(point_ids >= 0))
        self._velocity = None
        if self._lost == 0 and last is not None and stamp_ns > last.stamp_ns:
            self._velocity = (T @ np.linalg.inv(last.T_camera_world), (stamp_ns - last.stamp_ns) * 1e-9)
        self._lost = 0
        frame = _Frame(self._index, stamp_ns, features, T, point_ids)
        self._last = frame
        keyframe_id = None
        with stage_timer(timings, "keyframe"):
            if not self.localisation_only and self._wants_keyframe(frame, tracked, timings):
                keyframe_id = self._insert_keyframe(frame)
                if self.wait_for_mapping:
                    self._wait_for_mapper(frame, timings, MAPPING_WAIT_S)
                elif tracked < 2 * self.settings.min_tracked:
                    self._wait_for_mapper(frame, timings, THIN_MAP_WAIT_S)
        return Tracked(TrackingState.TRACKING, "", T.copy(), tracked, rms, keyframe_id)

    def _follow_motion(self, last: _Frame, stamp_ns: int, features: FrameFeatures, point_ids: np.ndarray,
                       timings: dict[str, float]) -> tuple[np.ndarray | None, int]:
        """The pose refined from the last frame's points found around the constant-velocity prediction
        (the last motion scaled to this frame's time step) and its inliers; None under
        ``min_motion_matches`` found or ``min_motion_inliers`` inliers. Fills ``point_ids``."""
        s = self.settings
        with stage_timer(timings, "match"):
            predicted = last.T_camera_world
            if self._velocity is not None:
                predicted = extrapolated(last.T_camera_world, self._velocity, (stamp_ns - last.stamp_ns) * 1e-9)
            points, rows, keypoints = self._search_last(last, features, predicted)
        if len(rows) < s.min_motion_matches:
            return None, 0
        with stage_timer(timings, "pose"):
            refined = refine_pose(self.K, predicted, points.positions[rows], features.pixels[keypoints],
                                  features.sigmas[keypoints])
        inliers = int(np.count_nonzero(refined.inliers))
        if inliers < s.min_motion_inliers:
            return None, inliers
        point_ids[keypoints[refined.inliers]] = points.ids[rows[refined.inliers]]
        return refined.T_camera_world, inliers

    def _search_last(self, last: _Frame, features: FrameFeatures,
                     T: np.ndarray) -> tuple[PointArrays, np.ndarray, np.ndarray]:
        """The last frame's points, and ``(rows, keypoints)`` of those found around the predicted pose."""
        s = self.settings
        seen = np.flatnonzero(last.point_ids >= 0)
        points = self.map.arrays(last.point_ids[seen])
        seen = seen[np.isin(last.point_ids[seen], points.ids)]
        projected = project_points(points, T, self.K, self.size, self.map.scale_factor, self.map.levels)
        available = np.ones(len(features), bool)
        for window in (s.motion_window_px, 2 * s.motion_window_px):
            rows, keypoints = search_projected(points, projected, features, available, window, self.map.scale_factor,
                                               s.projection_max_distance, s.motion_ratio)
            consistent = rotation_consistent(last.features.angles[seen[rows]], features.angles[keypoints])
            rows, keypoints = rows[consistent], keypoints[consistent]
            if len(rows) >= s.min_motion_matches:
                break
        return points, rows, keypoints

    def _relocate(self, last: _Frame | None, features: FrameFeatures, point_ids: np.ndarray,
                  timings: dict[str, float]) -> tuple[np.ndarray | None, str]:
        """A pose from descriptor matches with the local map of the last tracked frame by PnP RANSAC
        then refinement, or from the whole map after a lost frame (``relocalisation.Relocaliser``);
        None and why not when too few inliers. Fills ``point_ids``."""
        if self._lost or last is None:
            relocalised = self._relocaliser.relocalise(features, timings)
            point_ids[:] = relocalised.point_ids
            return relocalised.T_camera_world, relocalised.reason
        s = self.settings
        with stage_timer(timings, "match"):
            keyframes = self.covisibility.local_keyframes(last.point_ids[last.point_ids >= 0], s.local_keyframes)
            points = self.map.arrays(self.map.points_of(keyframes))
            rows, keypoints = match_descriptors(points.descriptors, features.descriptors, s.match_max_distance,
                                                s.match_ratio)
        with stage_timer(timings, "pose"):
            solved = solve_pnp(self.K, s, points.positions[rows], features, keypoints)
        if solved is None:
            return None, "too_few_matches"
        refined, used = solved
        point_ids[keypoints[used][refined.inliers]] = points.ids[rows[used][refined.inliers]]
        return refined.T_camera_world, ""

    def _may_bridge(self, last: _Frame, stamp_ns: int) -> bool:
        """Whether a frame at ``stamp_ns`` that could not be tracked may be bridged from ``last``."""
        return not self.localisation_only and 0 < stamp_ns - last.stamp_ns <= BRIDGE_MAX_S * 1e9

    def _bridge(self, last: _Frame, stamp_ns: int, features: FrameFeatures,
                timings: dict[str, float]) -> Tracked | None:
        """The frame bridged from the last tracked one (``bridging``), as a keyframe after the last frame made
        one, their matches' new points added, the mapper's copy of the map brought up to date; None when the
        pair does not give ``min_tracked`` points or the mapper is busy (the next frame tries again): asked
        first, as the search and the two-view fit cost a frame period or more."""
        if not self.mapper.idle:
            return None
        s = self.settings
        first = last.features
        a, b = search_by_projection(first.pixels, np.full(len(first), BRIDGE_WINDOW_PX), first.levels,
                                    first.descriptors, features.pixels, features.levels, features.descriptors,
                                    np.ones(len(features), bool), s.match_max_distance, s.init_ratio)
        consistent = rotation_consistent(first.angles[a], features.angles[b])
        a, b = a[consistent], b[consistent]
        distance = self._steady_speed() * (stamp_ns - last.stamp_ns) * 1e-9
        bridge = bridge_pair(self.K, last.T_camera_world, first.pixels[a], features.pixels[b],
                             self._map_positions(last.point_ids[a]), distance, self._late_bound)
        if bridge is None or np.count_nonzero(bridge.inliers) < s.min_tracked:
            return None
        made = self._insert_bridge(last, stamp_ns, features, bridge, a, b)
        keyframe = made[-1]
        point_ids = keyframe.point_ids.copy()
        self.mapper.resend()
        tracked = np.flatnonzero(point_ids >= 0)
        errors = reprojection_errors(self.K, bridge.T_camera_world, self.map.positions(point_ids[tracked]),
                                     features.pixels[tracked])
        self._velocity = (bridge.T_camera_world @ invert(last.T_camera_world), (stamp_ns - last.stamp_ns) * 1e-9)
        self._lost = 0
        self._last = _Frame(self._index, stamp_ns, features, bridge.T_camera_world, point_ids)
        for new in made:
            self.mapper.enqueue(new.id)
            if self.wait_for_mapping:
                self._wait_for_mapper(self._last, timings, MAPPING_WAIT_S)
        self._reference_keyframe = self._last_keyframe_id = keyframe.id
        self._last_keyframe_stamp = stamp_ns
        logger.info("frame %d bridged from frame %d: %d points, scale from %s", self._index, last.index,
                    len(tracked), "the map" if bridge.from_map else "the motion")
        return Tracked(TrackingState.TRACKING, "", bridge.T_camera_world.copy(), len(tracked),
                       float(np.sqrt(np.mean(errors**2))), keyframe.id)

    def _insert_bridge(self, last: _Frame, stamp_ns: int, features: FrameFeatures, bridge: Bridge, a: np.ndarray,
                       b: np.ndarray) -> list[Keyframe]:
        """The keyframes a bridge makes, oldest first (the last frame's unless it is one, then the new
        frame's), and its points: the map points of the last frame's matched keypoints observed by the new
        keyframe too, the other matches' points new. ``a``, ``b`` (N,): the matches' keypoints in the two
        frames."""
        a, b, points = a[bridge.inliers], b[bridge.inliers], bridge.points_world[bridge.inliers]
        with self.map.lock:
            made = []
            if self._last_keyframe_stamp == last.stamp_ns and self._last_keyframe_id in self.map.keyframes:
                before = self.map.keyframes[self._last_keyframe_id]
            else:
                before = self.map.add_keyframe(last.stamp_ns, last.T_camera_world, last.features, last.point_ids)
                made.append(before)
            point_ids = np.full(len(features), -1, np.int64)
            seen = before.point_ids[a] >= 0
            point_ids[b[seen]] = before.point_ids[a[seen]]
            keyframe = self.map.add_keyframe(stamp_ns, bridge.T_camera_world, features, point_ids)
            for position, i, j in zip(points[~seen], a[~seen], b[~seen], strict=True):
                self.map.add_point(position, {before.id: int(i), keyframe.id: int(j)})
        return [*made, keyframe]

    def _steady_speed(self) -> float:
        """The camera's speed over the map's last ``SPEED_KEYFRAMES`` keyframes (bundle adjusted, so steadier
        than one frame's step): their path's length over its time, map units per second; NaN (no bridge
        scaled by motion) when their stamps span no time, or when the last frame's step says otherwise by
        more than ``SPEED_AGREEMENT`` either way: a camera that is not moving steadily (a hand-held one
        turning, keyframes bunched before a loss) gives no distance to trust."""
        if self._velocity is None:
            return float("nan")
        with self.map.lock:
            keyframes = sorted(self.map.keyframes.values(), key=lambda keyframe: keyframe.stamp_ns)[-SPEED_KEYFRAMES:]
        span_s = (keyframes[-1].stamp_ns - keyframes[0].stamp_ns) * 1e-9
        if not span_s > 0:
            return float("nan")
        centres = np.array([keyframe.centre for keyframe in keyframes])
        speed = float(np.sum(np.linalg.norm(np.diff(centres, axis=0), axis=1)) / span_s)
        delta, dt = self._velocity
        step = float(np.linalg.norm(delta[:3, 3])) / dt
        return speed if 1 / SPEED_AGREEMENT <= step / speed <= SPEED_AGREEMENT else float("nan")

    def _map_positions(self, point_ids: np.ndarray) -> np.ndarray:
        """(N, 3) world: the positions of map points ``point_ids`` (N,), NaN rows where -1 or gone."""
        positions = np.full((len(point_ids), 3), np.nan)
        known = np.flatnonzero(point_ids >= 0)
        points = self.map.arrays(point_ids[known])
        rows = known[np.isin(point_ids[known], points.ids)]
        positions[rows] = points.positions
        return positions

    def _track_local_map(self, T: np.ndarray, features: FrameFeatures,
                         point_ids: np.ndarray) -> tuple[np.ndarray, float] | None:
        """Search the local map's points around pose ``T`` and refine on every match; ``point_ids``
        keeps the inliers. Returns the refined pose and its RMS, px; None under ``min_tracked`` inliers."""
        s = self.settings
        keyframes = self.covisibility.local_keyframes(point_ids[point_ids >= 0], s.local_keyframes)
        if keyframes:
            self._reference_keyframe = keyframes[0]
        local = self.map.points_of(keyframes)
        points = self.map.arrays(local[~np.isin(local, point_ids)])
        projected = project_points(points, T, self.K, self.size, self.map.scale_factor, self.map.levels)
        rows, keypoints = search_projected(points, projected, features, point_ids < 0, s.local_window_px,
                                           self.map.scale_factor, s.projection_max_distance, s.local_ratio)
        point_ids[keypoints] = points.ids[rows]
        matched = np.flatnonzero(point_ids >= 0)
        everything = self.map.arrays(point_ids[matched])
        matched = matched[np.isin(point_ids[matched], everything.ids)]
        refined = refine_pose(self.K, T, everything.positions, features.pixels[matched], features.sigmas[matched])
        self.map.count_visible(points.ids[projected.rows])
        self.map.count_visible(everything.ids, refined.inliers)
        point_ids[:] = -1
        point_ids[matched[refined.inliers]] = everything.ids[refined.inliers]
        if np.count_nonzero(refined.inliers) < s.min_tracked:
            return None
        return refined.T_camera_world, float(refined.rms_px)

    def _wants_keyframe(self, frame: _Frame, tracked: int, timings: dict[str, float]) -> bool:
        """The keyframe decision for ``frame``; the milliseconds waited for the mapper go to ``timings``
        (``mapping_wait``) when it waited."""
        with self.map.lock:
            reference = self.map.keyframes.get(self._reference_keyframe)
            least = 2 if len(self.map.keyframes) <= 2 else 3
            seen = [] if reference is None else map(self.map.points.get,
                                                    reference.point_ids[reference.point_ids >= 0].tolist())
            reference_tracked = sum(1 for point in seen if point is not None and len(point.observations) >= least)
        decision = keyframe_decision(self.settings, abs(frame.stamp_ns - self._last_keyframe_stamp) * 1e-9, tracked,
                                     reference_tracked)
        idle = self.mapper.idle  # asked at every decision: it brings in what the mapping process sent back
        if idle and self._young_keyframe_due(frame):
            return True
        return decision is KeyframeDecision.YES or (decision is KeyframeDecision.IF_IDLE and idle)

    def _young_keyframe_due(self, frame: _Frame) -> bool:
        """Whether the map is young and ``frame``'s camera centre is at least the first two keyframes'
        distance from the last keyframe's; the map stops being young at ``young_map_keyframes`` keyframes."""
        if self._young_baseline is None:
            return False
        with self.map.lock:
            last = self.map.keyframes.get(self._last_keyframe_id)
            grown = len(self.map.keyframes) >= self.settings.young_map_keyframes
        if grown:
            self._young_baseline = None
            return False
        centre = invert(frame.T_camera_world)[:3, 3]
        return last is None or float(np.linalg.norm(centre - last.centre)) >= self._young_baseline

    def _wait_for_mapper(self, frame: _Frame, timings: dict[str, float], limit_s: float) -> None:
        """Wait for the mapper to be idle, at most ``limit_s`` (``MAPPING_WAIT_S`` in a lossless run, where a
        mapper still busy then gets a warning line; ``THIN_MAP_WAIT_S`` in real time); the milliseconds
        waited go to ``timings`` (``mapping_wait``)."""
        started = time.perf_counter()
        idle = self.mapper.wait_idle(limit_s)
        timings["mapping_wait"] = (time.perf_counter() - started) * 1e3
        if not idle and limit_s >= MAPPING_WAIT_S:
            logger.warning("frame %d: the mapper was still busy after %.0f s of waiting; tracking goes on",
                           frame.index, limit_s)

    def _insert_keyframe(self, frame: _Frame) -> int:
        keyframe = self.map.add_keyframe(frame.stamp_ns, frame.T_camera_world, frame.features, frame.point_ids)
        self._reference_keyframe = keyframe.id
        self._last_keyframe_stamp = frame.stamp_ns
        self._last_keyframe_id = keyframe.id
        self.mapper.enqueue(keyframe.id)
        return keyframe.id
