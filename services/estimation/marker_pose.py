"""Planar-marker poses of one camera, frame after frame: ``T_camera_marker`` and ``T_camera_<map>``.

Input per frame: detected marker ids, their corners in distorted pixels (ArUco order TL, TR,
BR, BL), side lengths and the calibration. The corners are undistorted once
(``cv2.undistortPoints(..., P=K)``); everything after works on a distortion-free pinhole.

Methods (``method``):

* ``"lm"``: normalised DLT homography of the corners, pose from the homography, then
  Levenberg-Marquardt on the reprojection error (``services.geometry.refine``); it starts from
  the best IPPE candidate instead when the homography pose puts a corner behind the camera.
* ``"ippe"``: OpenCV's IPPE_SQUARE (``cv2.solvePnPGeneric``) alone.
* ``"ippe+lm"`` (default): the IPPE candidate refined by the same LM.

Accuracy (``python -m tests.accuracy.report``; synthetic ``markers`` scene, 640x480, markers
5-30 % of the image width, median / p90 rotation error in degrees, median translation error in
% of distance). Exact corners + 0.5 px Gaussian noise per axis, 833 views: raw homography
10.5 / 22.0 / 1.58 %, OpenCV's solvePnP IPPE_SQUARE 2.75 / 12.2 / 0.55 %, ``ippe`` 2.74 / 10.7
/ 0.55 %, ``lm`` and ``ippe+lm`` 2.64 / 10.5 / 0.55 %. Rendered frames, ArucoDetector subpixel
corners, 332 views: homography 0.94 / 2.5 / 0.49 %, OpenCV 0.23 / 0.88 / 0.52 %, ``ippe`` the
same, ``lm`` and ``ippe+lm`` 0.21 / 0.80 / 0.52 % (the detector's corners sit 0.5 % inside the
true ones, so every method places markers 0.5 % too far). Board pose from its 6 markers, noisy
corners: IPPE on all corners 0.54 / 1.9 / 0.09 %, refined 0.34 / 0.89 / 0.07 % (cv2.solvePnP's
iterative method reaches the same optimum). The two refined methods reach the same
optimum from different starts; ``ippe+lm`` is the default because it starts closer and so
takes about 30 % less time (1.0 against 1.4 ms per marker on a 2-core VM).

Planar ambiguity: both IPPE candidates are always computed. When the second's reprojection
RMS is below ``ambiguity_ratio`` times the best's, the pose is flagged ``ambiguous`` and, if
this target's track is anchored and at most ``prior_max_age`` frames old, the candidate whose
rotation is closest to the track's wins; otherwise the lower error wins. A track is anchored
when its pose was unambiguous or was itself chosen by an anchored track, so a guess never
propagates (ArUco's MarkerPoseTracker idea). The refined methods refine both candidates when
the pose is ambiguous (dropping one that does not converge), only one otherwise.
``ambiguity_ratio`` = 2 minimised the error tail on the noisy views (4 seeds, 6650 views, p90
rotation error with the ``ippe`` method: lower error always 12.7 deg, ratio 1.25 11.4, 2 10.9,
2.5 12.5, 4 13.6): a wider band hands more poses to the track, which is itself noisy.

Marker maps (``marker_map``): the map's pose ``T_camera_<name>`` comes from all visible corners of
its markers at once. Its candidates are OpenCV's IPPE (and, for ``lm``, the homography) on all
corners when the visible corners are coplanar; otherwise each visible marker's IPPE_SQUARE
candidates composed with ``T_map_marker^-1``, of which the lowest RMS over all corners is kept.
The same ambiguity test and LM follow. A map's markers get no pose of their own (the map's pose
and ``T_map_marker`` give it), and their side lengths come from the map, not the detections.

Failures (no pose, never an exception), counted per marker or map by reason:
``no_side_length`` (side <= 0 or not finite), ``duplicate_id`` (an id detected twice in one
frame), ``degenerate_corners`` (not finite, coincident, collinear, zero-area, non-convex or
mirrored quadrilateral), ``degenerate_homography`` (the DLT or OpenCV's IPPE finds no
homography), ``behind_camera`` (no candidate has every corner in front), ``not_converged``,
``ill_conditioned`` (the corners leave the pose undetermined).

Poses carry the RMS of the corner residual lengths (undistorted pixels), the number of corners
used, the ambiguity flag and the 6x6 covariance ``refine.pose_covariance`` gives for independent
Gaussian corner noise of ``corner_sigma_px`` per axis (default 0.5 px, the accuracy tests' noise
model; ArUco subpixel corners on the synthetic scene do better, median error under 0.3 px, see
tests/unit/test_scenes_markers.py).
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from services.estimation.marker_map import MarkerMap, marker_corners
from services.geometry.camera import UNDISTORT_CRITERIA
from services.geometry.homography import DegenerateError, homography_dlt, pose_from_homography
from services.geometry.refine import pose_covariance, refine_pose, residuals_and_jacobian
from services.geometry.rotation import matrix_from_rotvec, rotation_angle
from services.geometry.se3 import invert, make_transform, transform_points

METHODS = ("lm", "ippe", "ippe+lm")
DEFAULT_METHOD = "ippe+lm"
PLANARITY = 0.01
"""Visible map corners are coplanar when all lie within this fraction of their RMS radius of one plane."""
MIN_TURN = 1e-6
"""A quadrilateral's turn at each corner (edge cross product) must exceed this fraction of its mean squared edge."""


@dataclass(frozen=True)
class TargetPose:
    """One target's pose in one frame.

    ``target``: ``"marker/<id>"`` or the map's name; ``T``: (4, 4) ``T_camera_target``;
    ``rms_px``: RMS corner residual length, undistorted pixels; ``points``: corners used;
    ``ambiguous``: another pose explains the corners almost as well; ``covariance``: (6, 6) over
    (tx, ty, tz, rx, ry, rz) in the target frame, metres and radians; ``marker_ids``: the
    markers that contributed.
    """

    target: str
    T: np.ndarray
    rms_px: float
    points: int
    ambiguous: bool
    covariance: np.ndarray
    marker_ids: tuple[int, ...]


@dataclass(frozen=True)
class FrameEstimate:
    """``poses``: one per target with a pose; ``failures``: reason -> count of markers or maps without one."""

    poses: list[TargetPose]
    failures: Counter[str]


@dataclass(frozen=True)
class Observation:
    """A target's correspondences: (M, 3) ``points`` in the target frame, (M, 2) undistorted ``pixels``;
    ``markers``: per visible marker, its ``T_target_marker`` and side length (4 rows each, in order)."""

    target: str
    marker_ids: tuple[int, ...]
    points: np.ndarray
    pixels: np.ndarray
    markers: tuple[tuple[np.ndarray, float], ...]


@dataclass(frozen=True)
class Candidate:
    """A pose hypothesis ``T`` (4, 4) with its RMS residual, and, once refined, its (2M, 6) Jacobian
    and convergence."""

    T: np.ndarray
    rms_px: float
    jacobian: np.ndarray | None = None
    converged: bool = True


@dataclass(frozen=True)
class Track:
    """A target's last pose: the estimator's frame number, ``T`` (4, 4), and whether it is anchored
    (unambiguous, or chosen by an anchored track)."""

    frame: int
    T: np.ndarray
    anchored: bool


class MarkerPoseEstimator:
    """Marker and marker-map poses of one camera; keeps each target's last pose to resolve ambiguities."""

    def __init__(self, method: str = DEFAULT_METHOD, marker_map: MarkerMap | None = None,
                 corner_sigma_px: float = 0.5, ambiguity_ratio: float = 2.0, prior_max_age: int = 5,
                 max_iterations: int = 100):
        if method not in METHODS:
            raise ValueError(f"method {method!r}: must be one of {', '.join(METHODS)}")
        if not (corner_sigma_px > 0 and ambiguity_ratio >= 1 and prior_max_age >= 0 and max_iterations >= 1):
            raise ValueError("need corner_sigma_px > 0, ambiguity_ratio >= 1, prior_max_age >= 0, max_iterations >= 1")
        self.method = method
        self.marker_map = marker_map
        self.corner_sigma_px = corner_sigma_px
        self.ambiguity_ratio = ambiguity_ratio
        self.prior_max_age = prior_max_age
        self.max_iterations = max_iterations
        self._frame = 0
        self._tracks: dict[str, Track] = {}

    def reset(self) -> None:
        """Forget every target's previous pose."""
        self._tracks.clear()

    def estimate(self, ids: Sequence[int], corners: np.ndarray, side_lengths: Sequence[float] | float,
                 K: np.ndarray, dist: np.ndarray | None = None) -> FrameEstimate:
        """Poses of one frame.

        ``ids``: (N,) int; ``corners``: (N, 4, 2) float distorted pixels, ArUco order TL, TR, BR, BL;
        ``side_lengths``: (N,) metres (or one number for all; 0 = unknown); ``K``: (3, 3);
        ``dist``: OpenCV distortion coefficients or None.
        """
        K = np.asarray(K, dtype=np.float64)
        if K.shape != (3, 3):
            raise ValueError(f"K must be (3, 3), got {K.shape}")
        self._frame += 1
        ids = np.asarray(ids, dtype=np.int64).reshape(-1)
        corners = np.asarray(corners, dtype=np.float64).reshape(len(ids), 4, 2)
        sides = np.broadcast_to(np.asarray(side_lengths, dtype=np.float64), ids.shape)
        failures: Counter[str] = Counter()
        counts = Counter(ids.tolist())
        finite = np.all(np.isfinite(corners), axis=(1, 2))
        undistorted = undistort(np.where(finite[:, None, None], corners, 0.0), K, dist)
        valid = finite & np.array([quadrilateral_is_valid(c) for c in undistorted], dtype=bool)
        in_map = self.marker_map.markers if self.marker_map else {}
        singles, map_rows = [], []
        for n, marker_id in enumerate(ids.tolist()):
            if counts[marker_id] > 1:
                failures["duplicate_id"] += 1
            elif not valid[n]:
                failures["degenerate_corners"] += 1
            elif marker_id in in_map:
                map_rows.append(n)
            elif not (math.isfinite(sides[n]) and sides[n] > 0):
                failures["no_side_length"] += 1
            else:
                singles.append(single_observation(marker_id, float(sides[n]), undistorted[n]))
        if map_rows:
            singles.append(map_observation(self.marker_map, ids[map_rows], undistorted[map_rows]))
        poses = []
        for observation in singles:
            pose = self._solve(observation, K)
            if isinstance(pose, str):
                failures[pose] += 1
            else:
                poses.append(pose)
        return FrameEstimate(poses, failures)

    def _solve(self, observation: Observation, K: np.ndarray) -> TargetPose | str:
        """The target's pose, or the reason it has none; records the pose as the target's track."""
        try:
            candidates = ippe_candidates(observation, K)
        except DegenerateError:
            return "degenerate_homography"
        if not candidates:
            return "behind_camera"
        ambiguous = len(candidates) == 2 and candidates[1].rms_px < self.ambiguity_ratio * candidates[0].rms_px
        if not ambiguous:
            candidates = candidates[:1]
        if self.method != "ippe":
            starts = [c.T for c in candidates]
            if self.method == "lm" and not ambiguous and (plane := plane_frame(observation)) is not None:
                try:
                    T_homography = homography_pose(observation, plane, K)
                except DegenerateError:
                    return "degenerate_homography"
                if candidate(observation, T_homography, K) is not None:
                    starts = [T_homography]
            candidates = []
            for T in starts:
                try:
                    result = refine_pose(T, observation.points, observation.pixels, K, self.max_iterations)
                except DegenerateError:
                    return "ill_conditioned"
                candidates.append(Candidate(result.T, result.rms_px, result.jacobian, result.converged))
            candidates = [c for c in candidates if c.converged]
            if not candidates:
                return "not_converged"
        chosen, anchored = self._choose(observation.target, candidates, ambiguous)
        if chosen.jacobian is None:
            chosen = Candidate(chosen.T, chosen.rms_px, residuals_and_jacobian(
                chosen.T, observation.points, observation.pixels, K)[1])
        try:
            covariance = pose_covariance(chosen.jacobian, self.corner_sigma_px)
        except DegenerateError:
            return "ill_conditioned"
        self._tracks[observation.target] = Track(self._frame, chosen.T, anchored)
        return TargetPose(observation.target, chosen.T, chosen.rms_px, len(observation.points), ambiguous,
                          covariance, observation.marker_ids)

    def _choose(self, target: str, candidates: list[Candidate], ambiguous: bool) -> tuple[Candidate, bool]:
        """The candidate closest in rotation to the target's anchored track when the pose is ambiguous
        and the track is recent, else the lowest RMS; and whether the choice is anchored."""
        track = self._tracks.get(target)
        if ambiguous and len(candidates) > 1 and track is not None and track.anchored \
                and self._frame - track.frame <= self.prior_max_age:
            return min(candidates, key=lambda c: rotation_angle(c.T[:3, :3], track.T[:3, :3])), True
        return min(candidates, key=lambda c: c.rms_px), not ambiguous


def quadrilateral_is_valid(corners: np.ndarray) -> bool:
    """Whether (4, 2) pixels form a finite, strictly convex quadrilateral turning the way a marker seen
    from the front does (TL, TR, BR, BL clockwise on screen, image y down)."""
    if not np.all(np.isfinite(corners)):
        return False
    edges = np.roll(corners, -1, axis=0) - corners
    turns = edges[:, 0] * np.roll(edges, -1, axis=0)[:, 1] - edges[:, 1] * np.roll(edges, -1, axis=0)[:, 0]
    scale = np.mean(np.sum(edges**2, axis=1))
    return bool(scale > 0 and np.all(turns > MIN_TURN * scale))


def undistort(corners: np.ndarray, K: np.ndarray, dist: np.ndarray | None) -> np.ndarray:
    """(N, 4, 2) undistorted pixels (same K) of (N, 4, 2) distorted ones."""
    if dist is None or len(corners) == 0 or not np.any(dist):
        return corners.copy()
    points = cv2.undistortPoints(corners.reshape(-1, 1, 2), np.asarray(K, dtype=np.float64),
                                 np.asarray(dist, dtype=np.float64), P=np.asarray(K, dtype=np.float64),
                                 criteria=UNDISTORT_CRITERIA)
    return points.reshape(corners.shape)


def single_observation(marker_id: int, length: float, pixels: np.ndarray) -> Observation:
    """The observation of one marker on its own (target ``marker/<id>``, target frame = marker frame)."""
    return Observation(f"marker/{marker_id}", (marker_id,), marker_corners(length), pixels, ((np.eye(4), length),))


def map_observation(marker_map: MarkerMap, ids: np.ndarray, pixels: np.ndarray) -> Observation:
    """The observation of a map from its visible markers' ``ids`` (K,) and (K, 4, 2) undistorted ``pixels``."""
    markers = [marker_map.markers[int(i)] for i in ids]
    return Observation(marker_map.name, tuple(int(i) for i in ids), np.concatenate([m.corners() for m in markers]),
                       pixels.reshape(-1, 2), tuple((m.T_map_marker, m.length) for m in markers))


def plane_frame(observation: Observation) -> np.ndarray | None:
    """(4, 4) ``T_target_plane`` whose z = 0 plane holds the observed points (z towards the markers'
    front), or None when they are not coplanar (see ``PLANARITY``)."""
    if len(observation.markers) == 1:
        return observation.markers[0][0]
    points = observation.points
    centre = points.mean(axis=0)
    _, _, Vt = np.linalg.svd(points - centre)
    radius = np.sqrt(np.mean(np.sum((points - centre) ** 2, axis=1)))
    if np.max(np.abs((points - centre) @ Vt[2])) > PLANARITY * radius:
        return None
    front = sum(T[:3, 2] for T, _ in observation.markers)
    normal = Vt[2] if front @ Vt[2] > 0 else -Vt[2]
    return make_transform(np.column_stack([Vt[0], np.cross(normal, Vt[0]), normal]), centre)


def in_plane(observation: Observation, T_target_plane: np.ndarray) -> np.ndarray:
    """(M, 3) observed points in the plane frame, z set to exactly 0."""
    points = transform_points(invert(T_target_plane), observation.points)
    points[:, 2] = 0.0
    return points


def candidate(observation: Observation, T: np.ndarray, K: np.ndarray) -> Candidate | None:
    """``T_camera_target`` scored on all the observation's points; None when a point is behind the camera."""
    points = transform_points(T, observation.points)
    if np.any(points[:, 2] <= 0):
        return None
    residuals = (points[:, :2] / points[:, 2:]) @ K[:2, :2].T + K[:2, 2] - observation.pixels
    return Candidate(T, float(np.sqrt(np.sum(residuals**2) / len(points))))


def ippe_candidates(observation: Observation, K: np.ndarray) -> list[Candidate]:
    """Up to two ``T_camera_target`` candidates, lowest RMS first, every point in front of the camera.

    Coplanar points: OpenCV's two IPPE solutions (IPPE_SQUARE for one marker) in the plane
    frame. Otherwise each marker's IPPE_SQUARE solutions composed with ``T_target_marker^-1``,
    of which only the best over all points is kept.
    """
    plane = plane_frame(observation)
    if plane is not None:
        flags = cv2.SOLVEPNP_IPPE_SQUARE if len(observation.markers) == 1 else cv2.SOLVEPNP_IPPE
        T_plane_target = invert(plane)
        poses = [T @ T_plane_target for T in solve_ippe(in_plane(observation, plane), observation.pixels, K, flags)]
    else:
        poses = []
        for n, (T_target_marker, length) in enumerate(observation.markers):
            pixels = observation.pixels[4 * n:4 * n + 4]
            T_marker_target = invert(T_target_marker)
            poses += [T @ T_marker_target for T in solve_ippe(marker_corners(length), pixels, K,
                                                              cv2.SOLVEPNP_IPPE_SQUARE)]
    scored = sorted((c for T in poses if (c := candidate(observation, T, K)) is not None), key=lambda c: c.rms_px)
    return scored if plane is not None else scored[:1]


def solve_ippe(points: np.ndarray, pixels: np.ndarray, K: np.ndarray, flags: int) -> list[np.ndarray]:
    """``T_camera_plane`` solutions (4, 4) of cv2.solvePnPGeneric for (M, 3) plane points (z = 0);
    DegenerateError when OpenCV refuses the points."""
    try:
        _, rvecs, tvecs, _ = cv2.solvePnPGeneric(points, pixels, K, None, flags=flags)
    except cv2.error as error:
        raise DegenerateError(f"IPPE found no pose: {error.err}") from error
    return [make_transform(matrix_from_rotvec(r), t) for r, t in zip(rvecs, tvecs, strict=True)]


def homography_pose(observation: Observation, T_target_plane: np.ndarray, K: np.ndarray) -> np.ndarray:
    """``T_camera_target`` from the normalised DLT homography of the coplanar points (DegenerateError if none)."""
    H = homography_dlt(in_plane(observation, T_target_plane)[:, :2], observation.pixels)
    return pose_from_homography(H, K) @ invert(T_target_plane)
