"""Local mapping: what happens to the map when a keyframe arrives, away from the tracking of frames.

For each new keyframe, in order (ORB-SLAM's local mapping):

1. Cull recent points that failed (``map.cleaner.LocalMapCleaner``).
2. Triangulate new points between the keyframe's unmatched keypoints and those of its best
   covisible keyframes: descriptor matches within a chi-square bound of the epipolar line, on the
   half of it where the rays meet in front of both cameras,
   triangulated (``services.geometry.triangulation.triangulate_many``), kept when in front of both
   cameras, seen under enough parallax, within a chi-square bound of both observations and at
   distances that agree with their pyramid levels.
3. Fuse duplicates: the keyframe's points projected into its neighbours (and theirs into it); a
   match with a keypoint that has another point merges the two, one without adds an observation.
4. Local bundle adjustment (``services.slam.optimisation.bundle_adjust``) of the keyframe, its
   covisible keyframes and their points, every other keyframe observing those points fixed; the
   observations it finds to be outliers are removed.
5. With ``loop_closing``: loop detection, and when a loop is found its correction, pose graph and
   global bundle adjustment (``services.slam.loop.closing``; the ``loop_closing`` stage, its records in
   ``loop_closer.closures``); skipped, as fusion is, while other keyframes wait.
6. Once, when the map holds ``calibration_check.CHECK_KEYFRAMES`` keyframes: the camera matrix
   checked against the map (``calibration_check.check_focal``, about 80-200 ms), its outcome in
   ``focal_check`` for the tracker to report, so that no frame waits for it.

``LocalMapper`` runs this on a thread fed by a queue (``threaded=True``), so that tracking never
waits for it unless it asks to (``wait_idle``), or inline in ``enqueue`` (deterministic, for tests).
It holds the map's lock only to take snapshots and to apply results, in short steps of at most
``SNAPSHOT_POINTS`` points that check what changed meanwhile: searches, triangulation, points'
summaries (``MapDatabase.refresh_points``) and the bundle adjustment's problem are computed outside it.
(A frame tracked between two steps of one result sees part of it applied, as a frame tracked between
two keyframes' results sees one.) A keyframe processed while others wait gets only steps 1 and 2.
"""

from __future__ import annotations

import dataclasses
import logging
import queue
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from enum import Enum
from typing import Protocol, TypeVar

import numpy as np

from services.geometry.camera import CameraModel
from services.geometry.camera_stack import CameraStack
from services.geometry.epipolar import fundamental_matrix, near_lines
from services.geometry.se3 import invert
from services.geometry.triangulation import meet_in_front, triangulate_many
from services.slam.calibration_check import CHECK_KEYFRAMES, FocalCheck, check_focal
from services.slam.loop.closing import LoopCloser
from services.slam.map.cleaner import LocalMapCleaner
from services.slam.map.covisibility import CovisibilityGraph
from services.slam.map.database import MapDatabase
from services.slam.map.keyframe import Keyframe
from services.slam.matching import match_candidates, rotation_consistent
from services.slam.optimisation import BundleProblem, bundle_adjust
from services.slam.projection import project_points, search_projected
from services.slam.settings import SlamSettings
from services.slam.timing import stage_timer

__all__ = ["CHI2_ONE_DOF", "CHI2_TWO_DOF", "KeyframeDecision", "LocalMapper", "MappedKeyframe", "Mapper",
           "keyframe_decision", "triangulation_checks"]

logger = logging.getLogger(__name__)
_Item = TypeVar("_Item")

CHI2_ONE_DOF, CHI2_TWO_DOF = 3.841, 5.991
"""95 % chi-square bounds: an epipolar distance has one degree of freedom, a reprojection error two."""
MIN_BASELINE_RATIO = 0.01
"""Keyframes closer than this fraction of the neighbour's median scene depth are not triangulated from."""
SCALE_SLACK = 1.5
FUSE_WINDOW_PX = 3.0
SNAPSHOT_POINTS = 256
"""The mapper reads or writes this many points per hold of the map's lock (the bundle adjustment's
problem and results, fusion's merges)."""


@dataclass(frozen=True)
class MappedKeyframe:
    """One keyframe's local mapping: ``stages`` ms (``LocalMapper.timings_ms``), ``wall_ms`` and ``cpu_ms``
    (the mapping thread's or process's CPU time), ``waiting`` other keyframes queued behind it then."""

    keyframe_id: int
    stages: dict[str, float]
    wall_ms: float
    cpu_ms: float
    waiting: int


class Mapper(Protocol):
    """What the tracker needs of a local mapper: ``LocalMapper`` (thread or inline) or
    ``mapping_process.MappingProcess``. ``history``: every keyframe mapped, oldest first."""

    history: list[MappedKeyframe]
    focal_check: FocalCheck | None
    """The camera matrix's check against the map, once the mapper made it (``calibration_check``)."""

    @property
    def idle(self) -> bool: ...

    def wait_idle(self, timeout_s: float) -> bool:
        """Block until no keyframe is waiting or being mapped (True), at most ``timeout_s`` seconds (False)."""
        ...

    def enqueue(self, keyframe_id: int) -> None: ...

    def adjust_initial_map(self, first: int, second: int) -> None: ...

    def resend(self) -> None:
        """The tracker changed the map itself (``bridging``), the mapper idle: bring its copy up to date."""

    def sync(self) -> None: ...

    def close(self) -> None: ...


class KeyframeDecision(Enum):
    """Whether a tracked frame becomes a keyframe: ``YES``, ``NO``, or ``IF_IDLE`` (only with the mapper idle)."""

    YES = "yes"
    NO = "no"
    IF_IDLE = "if_idle"


def keyframe_decision(settings: SlamSettings, seconds_since: float, tracked: int,
                      reference_tracked: int) -> KeyframeDecision:
    """Whether a tracked frame becomes a keyframe: it tracks ``tracked`` points where its reference
    keyframe tracks ``reference_tracked`` well-observed ones, ``seconds_since`` after the last
    keyframe. Under ``keyframe_ratio`` of the reference's points (new area in view) it does once
    ``max_keyframe_gap_s`` passed, and between ``min_keyframe_gap_s`` and that only if the mapper is
    idle (``IF_IDLE``); it always does when nearly lost (under twice ``min_tracked``)."""
    s = settings
    if tracked < 2 * s.min_tracked:
        return KeyframeDecision.YES
    if tracked >= s.keyframe_ratio * reference_tracked:
        return KeyframeDecision.NO
    if seconds_since >= s.max_keyframe_gap_s:
        return KeyframeDecision.YES
    return KeyframeDecision.IF_IDLE if seconds_since >= s.min_keyframe_gap_s else KeyframeDecision.NO


def triangulation_checks(points: np.ndarray, centres: np.ndarray, residuals: np.ndarray, depths: np.ndarray,
                         sigmas: np.ndarray, min_parallax_deg: float) -> np.ndarray:
    """(N,) bool: which of N points triangulated from two views are kept.

    ``points`` (N, 3) world; ``centres`` (2, 3) the two camera centres; ``residuals`` (N, 2, 2)
    observed - projected px; ``depths`` (N, 2); ``sigmas`` (N, 2) px per observation (their level
    scale). Kept: finite, in front of both cameras, rays at least ``min_parallax_deg`` apart, each
    reprojection within ``CHI2_TWO_DOF`` sigma^2, and distances to the two cameras in a ratio within
    ``SCALE_SLACK`` of the ratio of the two levels' scales."""
    finite = np.all(np.isfinite(points), axis=1)
    safe = np.where(finite[:, None], points, 0.0)
    rays = safe[:, None, :] - centres[None]
    lengths = np.linalg.norm(rays, axis=2)
    cos = np.sum(rays[:, 0] * rays[:, 1], axis=1) / np.maximum(lengths[:, 0] * lengths[:, 1], 1e-300)
    chi2 = np.sum(residuals**2, axis=2) / sigmas**2
    with np.errstate(divide="ignore", invalid="ignore"):
        distance_ratio = lengths[:, 0] / lengths[:, 1]
        level_ratio = sigmas[:, 0] / sigmas[:, 1]
        scale_ok = (distance_ratio * SCALE_SLACK >= level_ratio) & (distance_ratio <= level_ratio * SCALE_SLACK)
        in_front = np.all(depths > 0, axis=1)
    return (finite & in_front & (cos < np.cos(np.radians(min_parallax_deg))) & np.all(chi2 < CHI2_TWO_DOF, axis=1)
            & scale_ok)


class LocalMapper:
    """Processes new keyframes of ``slam_map`` (a camera of intrinsics ``K`` (3, 3), undistorted)."""

    def __init__(self, slam_map: MapDatabase, K: np.ndarray, size: tuple[int, int], settings: SlamSettings,
                 threaded: bool):
        self.map = slam_map
        self.covisibility = CovisibilityGraph(slam_map)
        self.cleaner = LocalMapCleaner(slam_map, settings)
        self.K = np.asarray(K, np.float64)
        self.size = size
        self.settings = settings
        self.history: list[MappedKeyframe] = []
        self.focal_check: FocalCheck | None = None
        """The camera matrix's check against the map (step 6), once made."""
        self.loop_closer = LoopCloser(slam_map, self.K, size, settings, self.adjust) if settings.loop_closing else None
        self._queue: queue.Queue[int | None] = queue.Queue()
        self._unfinished = 0
        """Keyframes handed to the thread and not mapped yet (under ``_finished``)."""
        self._finished = threading.Condition()
        self._thread: threading.Thread | None = None
        if threaded:
            self._thread = threading.Thread(target=self._run, name="slam-mapping", daemon=True)
            self._thread.start()

    @property
    def idle(self) -> bool:
        """No keyframe waiting or being processed (always, inline)."""
        with self._finished:
            return self._unfinished == 0

    def wait_idle(self, timeout_s: float) -> bool:
        """Block until the thread has mapped every keyframe handed to it (True), at most ``timeout_s``
        seconds (False); inline, True at once."""
        with self._finished:
            return self._finished.wait_for(lambda: self._unfinished == 0, timeout_s)

    def enqueue(self, keyframe_id: int) -> None:
        """Hand over a new keyframe: queued for the thread, or processed at once without one."""
        if self._thread is None:
            self.process(keyframe_id)
        else:
            with self._finished:
                self._unfinished += 1
            self._queue.put(keyframe_id)

    def close(self) -> None:
        """Stop the thread after the keyframes already queued."""
        if self._thread is not None:
            self._queue.put(None)
            self._thread.join()
            self._thread = None

    def sync(self) -> None:
        """Nothing to bring in: this mapper works on the tracker's own map."""

    def _run(self) -> None:
        while (keyframe_id := self._queue.get()) is not None:
            try:
                self.process(keyframe_id, others_waiting=not self._queue.empty())
            except Exception:
                logger.exception("local mapping failed on keyframe %d; the map stays as it was", keyframe_id)
            finally:
                with self._finished:
                    self._unfinished -= 1
                    self._finished.notify_all()

    def process(self, keyframe_id: int, others_waiting: bool = False,
                stepped: Callable[[], None] | None = None) -> None:
        """Cull, triangulate, fuse and adjust around keyframe ``keyframe_id``; its record (stage times) in ``history``.
        When more keyframes wait (``others_waiting``), fusion and bundle adjustment are left to the last
        of them (as ORB-SLAM does): new points for the tracker come first. ``stepped`` is called after
        each step the tracker should see at once: each neighbour's new points, and the fusion."""
        s = self.settings
        wall, cpu = time.perf_counter(), time.thread_time()
        timings: dict[str, float] = {}
        with stage_timer(timings, "cull"):
            self.cleaner.cull_points(keyframe_id)
        with stage_timer(timings, "triangulate"):
            self.triangulate(keyframe_id, stepped)
        if not others_waiting:
            with stage_timer(timings, "fuse"):
                self.fuse(keyframe_id)
            if stepped is not None:
                stepped()
            with stage_timer(timings, "bundle_adjustment"):
                with self.map.lock:
                    window = [keyframe_id] + self.covisibility.covisible(keyframe_id, s.ba_window - 1)
                self.adjust(window)
            if self.loop_closer is not None:
                with stage_timer(timings, "loop_closing"):
                    self.loop_closer.process(keyframe_id)
        self.history.append(MappedKeyframe(keyframe_id, timings, (time.perf_counter() - wall) * 1e3,
                                           (time.thread_time() - cpu) * 1e3, self._queue.qsize()))
        self.check_calibration()

    def check_calibration(self) -> None:
        """Step 6: check the camera matrix once the map holds ``CHECK_KEYFRAMES`` keyframes (once)."""
        if self.focal_check is not None or len(self.map.keyframes) < CHECK_KEYFRAMES:
            return
        started = time.perf_counter()
        check = check_focal(self.map, self.K, self.size)
        if check is not None:
            self.focal_check = dataclasses.replace(check, took_ms=(time.perf_counter() - started) * 1e3)

    def adjust_initial_map(self, first: int, second: int) -> None:
        """Bundle adjust the map's first two keyframes and points (the first fixed, and the scale)."""
        self.adjust([first, second])

    def resend(self) -> None:
        """Nothing to send: this mapper works on the tracker's own map."""

    def adjust(self, window: list[int], iterations: int | None = None) -> None:
        """Local bundle adjustment of the keyframes ``window`` and every point they observe; the other
        keyframes observing those points stay fixed (and the map's first keyframe: with fewer than two
        fixed, the scale is held too). Outlier observations are removed afterwards. ``iterations``:
        ``ba_iterations`` unless given (a global adjustment, every keyframe in ``window``)."""
        s = self.settings
        problem = self._problem(window)
        if problem is None:
            return
        try:
            result = bundle_adjust(problem, max_iterations=iterations or s.ba_iterations,
                                   fix_scale=len(problem.fixed) < 2)
        except ValueError as error:
            logger.warning("local bundle adjustment skipped: %s", error)
            return
        with self.map.lock:
            for keyframe_id, T in result.poses.items():
                if keyframe_id not in problem.fixed and keyframe_id in self.map.keyframes:
                    self.map.set_pose(keyframe_id, T)
        for moved in _chunks(list(result.points.items())):
            with self.map.lock:
                for point_id, position in moved:
                    self.map.set_position(point_id, position)
        outliers = list(zip(problem.frame_ids[result.outliers].tolist(), problem.point_ids[result.outliers].tolist(),
                            strict=True))
        for dropped in _chunks(outliers):
            with self.map.lock:
                for keyframe_id, point_id in dropped:
                    self.map.remove_observation(point_id, keyframe_id, refresh=False)
        self.map.refresh_points(np.unique(problem.point_ids[result.outliers]))

    def _problem(self, window: list[int]) -> BundleProblem | None:
        """The bundle adjustment of ``window``: the points and observations read under the map's lock,
        ``SNAPSHOT_POINTS`` points at a time, the arrays built without it; None without any point."""
        observations: list[tuple[int, list[tuple[int, int]]]] = []
        positions: dict[int, np.ndarray] = {}
        for chunk in _chunks(self.map.points_of(window).tolist()):
            with self.map.lock:
                for point_id in chunk:
                    point = self.map.points.get(point_id)
                    if point is not None:
                        observations.append((point_id, list(point.observations.items())))
                        positions[point_id] = point.position
        with self.map.lock:
            every_keyframe = dict(self.map.keyframes)
        if not positions:
            return None
        keyframes = {k: every_keyframe[k] for _, seen in observations for k, _ in seen}
        poses = {k: keyframe.T_camera_world for k, keyframe in keyframes.items()}
        first = min(every_keyframe)
        counts = np.array([len(seen) for _, seen in observations], np.int64)
        point_ids = np.repeat(np.array([p for p, _ in observations], np.int64), counts)
        frame_ids = np.array([k for _, seen in observations for k, _ in seen], np.int64)
        indices = np.array([i for _, seen in observations for _, i in seen], np.int64)
        pixels, sigmas = np.zeros((len(indices), 2)), np.zeros(len(indices))
        for keyframe_id, keyframe in keyframes.items():
            rows = np.flatnonzero(frame_ids == keyframe_id)
            pixels[rows] = keyframe.features.pixels[indices[rows]]
            sigmas[rows] = keyframe.features.sigmas[indices[rows]]
        fixed = (set(poses) - set(window)) | ({first} & set(poses))
        if not fixed:
            fixed = {min(poses)}
        return BundleProblem(K=self.K, poses={k: T.copy() for k, T in poses.items()},
                             points={p: x.copy() for p, x in positions.items()}, frame_ids=frame_ids,
                             point_ids=point_ids, pixels=pixels, fixed=frozenset(fixed), sigmas=sigmas)

    def triangulate(self, keyframe_id: int, stepped: Callable[[], None] | None = None) -> int:
        """New points between keyframe ``keyframe_id`` and its best covisible keyframes, best first; how
        many. ``stepped`` is called after each neighbour that gave new points."""
        s = self.settings
        made = 0
        for neighbour_id in self.covisibility.covisible(keyframe_id, s.triangulation_neighbours):
            with self.map.lock:
                keyframe, neighbour = self.map.keyframes[keyframe_id], self.map.keyframes.get(neighbour_id)
            if neighbour is None:
                continue
            pair = _Pair(keyframe, neighbour, self.map)
            if not pair.wide_enough():
                continue
            a, b = self._epipolar_matches(pair)
            if len(a) == 0:
                continue
            cameras = [CameraModel(str(k.id), 0, 0, self.K, np.zeros(5), invert(k.T_camera_world))
                       for k in (keyframe, neighbour)]
            stack = CameraStack.of(cameras)
            pixels = np.stack([keyframe.features.pixels[a], neighbour.features.pixels[b]], axis=1)
            found = triangulate_many(stack, pixels, np.ones((len(a), 2), bool), 1.0, ideal=pixels)
            sigmas = np.stack([keyframe.features.sigmas[a], neighbour.features.sigmas[b]], axis=1)
            centres = np.array([keyframe.centre, neighbour.centre])
            with np.errstate(invalid="ignore"):
                depths = stack.depths(np.nan_to_num(found.points))
            kept = triangulation_checks(found.points, centres, found.residuals, depths, sigmas, s.min_parallax_deg)
            added = self.map.add_points(found.points[kept], [{keyframe.id: int(i), neighbour.id: int(j)}
                                                             for i, j in zip(a[kept], b[kept], strict=True)])
            made += len(added)
            if added and stepped is not None:
                stepped()
        return made

    def _epipolar_matches(self, pair: _Pair) -> tuple[np.ndarray, np.ndarray]:
        """``(keypoints of the keyframe, keypoints of the neighbour)``: unmatched keypoint pairs whose
        descriptors match (distance, ratio, one per keypoint, consistent orientation), the neighbour's
        keypoint within the one-degree-of-freedom chi-square bound (its level's sigma) of the epipolar
        line of the keyframe's, and the two rays meeting in front of both cameras: candidates behind a
        camera are left out before the ratio test, where they would only crowd it."""
        s = self.settings
        first, second = pair.keyframe.features, pair.neighbour.features
        free_a = np.flatnonzero(pair.keyframe.point_ids < 0)
        free_b = np.flatnonzero(pair.neighbour.point_ids < 0)
        if len(free_a) == 0 or len(free_b) == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        F = fundamental_matrix(self.K, self.K, pair.T_neighbour_keyframe)
        bounds = (np.sqrt(CHI2_ONE_DOF) * second.sigmas[free_b]).astype(np.float32)
        rows, columns = near_lines(F, first.pixels[free_a], second.pixels[free_b], bounds)
        front = meet_in_front(self.K, pair.keyframe.T_camera_world, pair.neighbour.T_camera_world,
                              first.pixels[free_a], second.pixels[free_b], rows, columns)
        a, b = match_candidates(first.descriptors[free_a], second.descriptors[free_b], rows[front], columns[front],
                                s.triangulation_max_distance, s.triangulation_ratio)
        a, b = free_a[a], free_b[b]
        consistent = rotation_consistent(first.angles[a], second.angles[b])
        return a[consistent], b[consistent]

    def fuse(self, keyframe_id: int) -> int:
        """Merge the keyframe's points with duplicates in its covisible keyframes, both ways; how many
        observations were merged or added."""
        s = self.settings
        changed = 0
        neighbours = self.covisibility.covisible(keyframe_id, s.triangulation_neighbours)
        for source, target in [(keyframe_id, n) for n in neighbours] + [(n, keyframe_id) for n in neighbours]:
            with self.map.lock:
                if source not in self.map.keyframes or target not in self.map.keyframes:
                    continue
                points = self.map.arrays(self.map.points_of([source]))
                keyframe = self.map.keyframes[target]
                T, features, owners = keyframe.T_camera_world.copy(), keyframe.features, keyframe.point_ids.copy()
            points = self.map.arrays(points.ids[~np.isin(points.ids, owners)])
            projected = project_points(points, T, self.K, self.size, self.map.scale_factor, self.map.levels)
            rows, keypoints = search_projected(points, projected, features, np.ones(len(features), bool),
                                               FUSE_WINDOW_PX, self.map.scale_factor, s.triangulation_max_distance,
                                               1.0)
            touched: list[int] = []
            for chunk in _chunks(list(zip(points.ids[rows].tolist(), keypoints.tolist(), strict=True))):
                with self.map.lock:
                    for point_id, index in chunk:
                        if point_id not in self.map.points or target in self.map.points[point_id].observations:
                            continue
                        owner = int(keyframe.point_ids[index])
                        if owner < 0:
                            self.map.add_observation(point_id, target, index, refresh=False)
                            touched.append(point_id)
                        elif owner in self.map.points:
                            kept, merged = sorted((owner, point_id),
                                                  key=lambda p: -len(self.map.points[p].observations))
                            self.map.merge_points(kept, merged, refresh=False)
                            touched.append(kept)
                        changed += 1
            self.map.refresh_points(np.unique(np.array(touched, np.int64)))
        return changed


def _chunks(items: list[_Item]) -> Iterator[list[_Item]]:
    """``items`` in runs of ``SNAPSHOT_POINTS``: one hold of the map's lock each."""
    for start in range(0, len(items), SNAPSHOT_POINTS):
        yield items[start:start + SNAPSHOT_POINTS]


class _Pair:
    """A keyframe and a neighbour to triangulate from (copies of their poses)."""

    def __init__(self, keyframe: Keyframe, neighbour: Keyframe, slam_map: MapDatabase):
        self.keyframe, self.neighbour = keyframe, neighbour
        self.T_neighbour_keyframe = neighbour.T_camera_world @ invert(keyframe.T_camera_world)
        seen = neighbour.point_ids[neighbour.point_ids >= 0]
        positions = slam_map.positions(seen)
        depths = positions @ neighbour.T_camera_world[2, :3] + neighbour.T_camera_world[2, 3]
        self.median_depth = float(np.median(depths)) if len(depths) else np.inf

    def wide_enough(self) -> bool:
        baseline = float(np.linalg.norm(self.T_neighbour_keyframe[:3, 3]))
        return baseline > MIN_BASELINE_RATIO * self.median_depth
