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
optimum from different starts; ``ippe+lm`` is the default because it starts closer and needs
no homography per marker, so it takes less than half the time of ``lm``.

Speed: the single markers of a frame are solved together. Each still gets its own OpenCV IPPE
call, but the candidates of all of them are scored in one batch, all their LM refinements run
as one ``refine_poses`` batch (whose problems advance in lockstep, each exactly as it would
alone) and their covariances come from one call on the LM's ``J^T J``; the map is a second
batch. A frame of about 6 markers costs about 1.3 ms (``ippe+lm``; 4.9 ms marker by marker
before; 640x480 ``markers`` scene, 2-core VM), of which OpenCV's IPPE is about 0.1 ms; each
marker's pose is exactly the one it gets alone (tests/unit/test_estimation_marker_pose.py).

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
used, the ambiguity flag and the 6x6 covariance ``refine.pose_covariances`` gives for independent
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
from services.geometry.refine import pose_covariances, refine_poses, residuals_and_jacobians
from services.geometry.rotation import rotation_angle
from services.geometry.se3 import invert, make_transform, transform_points

METHODS = ("lm", "ippe", "ippe+lm")
DEFAULT_METHOD = "ippe+lm"
PLANARITY = 0.01
"""Visible map corners are coplanar when all lie within this fraction of their RMS radius of one plane."""
MIN_TURN = 1e-6
"""A quadrilateral's turn at each corner (edge cross product) must exceed this fraction of its mean squared edge."""
NEXT_CORNER = np.array([1, 2, 3, 0])
IDENTITY = np.eye(4)
IDENTITY.flags.writeable = False


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
    ``markers``: per visible marker, its ``T_target_marker`` (4, 4) and its (4, 3) corners in its own
    frame (4 rows each of ``points`` and ``pixels``, in order)."""

    target: str
    marker_ids: tuple[int, ...]
    points: np.ndarray
    pixels: np.ndarray
    markers: tuple[tuple[np.ndarray, np.ndarray], ...]


@dataclass(frozen=True)
class Candidate:
    """A pose hypothesis ``T`` (4, 4) with its RMS residual, and, once refined, ``J^T J`` (6, 6) of its
    residual Jacobian there."""

    T: np.ndarray
    rms_px: float
    normal: np.ndarray | None = None


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
        sides = (np.zeros(len(ids)) + np.asarray(side_lengths, dtype=np.float64)).tolist()
        failures: Counter[str] = Counter()
        counts = Counter(ids.tolist())
        finite = np.isfinite(corners).all(axis=(1, 2))
        if not finite.all():
            corners = np.where(finite[:, None, None], corners, 0.0)
        undistorted = undistort(corners, K, dist)
        valid = (finite & quadrilaterals_are_valid(undistorted)).tolist()
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
                singles.append(single_observation(marker_id, sides[n], undistorted[n]))
        groups = [singles]
        if map_rows:
            groups.append([map_observation(self.marker_map, ids[map_rows], undistorted[map_rows])])
        poses = []
        for group in groups:
            for pose in self._solve(group, K):
                if isinstance(pose, str):
                    failures[pose] += 1
                else:
                    poses.append(pose)
        return FrameEstimate(poses, failures)

    def _solve(self, observations: list[Observation], K: np.ndarray) -> list[TargetPose | str]:
        """Per observation (all of one point count, solved together), its target's pose or the reason it
        has none; records each pose as its target's track."""
        if not observations:
            return []
        reasons: dict[int, str] = {}
        found: dict[int, list[Candidate]] = {}
        ambiguous: dict[int, bool] = {}
        for i, candidates in enumerate(ippe_candidates(observations, K)):
            if candidates is None:
                reasons[i] = "degenerate_homography"
            elif not candidates:
                reasons[i] = "behind_camera"
            else:
                ambiguous[i] = len(candidates) == 2 and \
                    candidates[1].rms_px < self.ambiguity_ratio * candidates[0].rms_px
                found[i] = candidates if ambiguous[i] else candidates[:1]
        if self.method != "ippe":
            found = self._refine(observations, found, ambiguous, K, reasons)
        chosen = {i: self._choose(observations[i].target, candidates, ambiguous[i])
                  for i, candidates in found.items()}
        if not chosen:
            return [reasons[i] for i in range(len(observations))]
        picked = [candidate for candidate, _ in chosen.values()]
        if self.method == "ippe":
            normals = normals_at(np.array([c.T for c in picked]), [observations[i] for i in chosen], K)
        else:
            normals = np.array([c.normal for c in picked])
        covariances, regular = pose_covariances(normals, self.corner_sigma_px)
        poses: dict[int, TargetPose] = {}
        for k, (i, (candidate, anchored)) in enumerate(chosen.items()):
            observation = observations[i]
            if not regular[k]:
                reasons[i] = "ill_conditioned"
                continue
            self._tracks[observation.target] = Track(self._frame, candidate.T, anchored)
            poses[i] = TargetPose(observation.target, candidate.T, candidate.rms_px, len(observation.points),
                                  ambiguous[i], covariances[k], observation.marker_ids)
        return [poses[i] if i in poses else reasons[i] for i in range(len(observations))]

    def _refine(self, observations: list[Observation], found: dict[int, list[Candidate]],
                ambiguous: dict[int, bool], K: np.ndarray, reasons: dict[int, str]) -> dict[int, list[Candidate]]:
        """The converged LM refinements of each observation's candidates (for ``lm`` and an unambiguous
        view, of its homography pose instead when that has every point in front), all run at once;
        an observation that gets none has its reason added to ``reasons``."""
        starts: list[tuple[int, np.ndarray]] = []
        for i, candidates in found.items():
            observation = observations[i]
            if self.method == "lm" and not ambiguous[i] and (plane := plane_frame(observation)) is not None:
                try:
                    T_homography = homography_pose(observation, plane, K)
                except DegenerateError:
                    reasons[i] = "degenerate_homography"
                    continue
                if reprojection_rms(T_homography[None], observation.points[None], observation.pixels[None],
                                    K)[0] != math.inf:
                    starts.append((i, T_homography))
                    continue
            starts += [(i, candidate.T) for candidate in candidates]
        if not starts:
            return {}
        rows = [i for i, _ in starts]
        result = refine_poses(np.array([T for _, T in starts]), np.array([observations[i].points for i in rows]),
                              np.array([observations[i].pixels for i in rows]), K, self.max_iterations)
        refined: dict[int, list[Candidate]] = {}
        for k, i in enumerate(rows):
            if result.degenerate[k]:
                reasons[i] = "ill_conditioned"
            elif result.converged[k]:
                refined.setdefault(i, []).append(Candidate(result.T[k], float(result.rms_px[k]), result.normal[k]))
        for i in rows:
            if i not in refined:
                reasons.setdefault(i, "not_converged")
        return {i: candidates for i, candidates in refined.items() if i not in reasons}

    def _choose(self, target: str, candidates: list[Candidate], ambiguous: bool) -> tuple[Candidate, bool]:
        """The candidate closest in rotation to the target's anchored track when the pose is ambiguous
        and the track is recent, else the lowest RMS; and whether the choice is anchored."""
        track = self._tracks.get(target)
        if ambiguous and len(candidates) > 1 and track is not None and track.anchored \
                and self._frame - track.frame <= self.prior_max_age:
            return min(candidates, key=lambda c: rotation_angle(c.T[:3, :3], track.T[:3, :3])), True
        return min(candidates, key=lambda c: c.rms_px), not ambiguous


def quadrilaterals_are_valid(corners: np.ndarray) -> np.ndarray:
    """(N,) bool: whether each of (N, 4, 2) finite pixels forms a strictly convex quadrilateral turning
    the way a marker seen from the front does (TL, TR, BR, BL clockwise on screen, image y down)."""
    edges = corners.take(NEXT_CORNER, axis=1) - corners
    following = edges.take(NEXT_CORNER, axis=1)
    turns = edges[..., 0] * following[..., 1] - edges[..., 1] * following[..., 0]
    scale = np.mean(np.sum(edges**2, axis=2), axis=1)
    return (scale > 0) & np.all(turns > MIN_TURN * scale[:, None], axis=1)


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
    corners = marker_corners(length)
    return Observation(f"marker/{marker_id}", (marker_id,), corners, pixels, ((IDENTITY, corners),))


def map_observation(marker_map: MarkerMap, ids: np.ndarray, pixels: np.ndarray) -> Observation:
    """The observation of a map from its visible markers' ``ids`` (K,) and (K, 4, 2) undistorted ``pixels``."""
    markers = [marker_map.markers[int(i)] for i in ids]
    return Observation(marker_map.name, tuple(int(i) for i in ids), np.concatenate([m.corners() for m in markers]),
                       pixels.reshape(-1, 2), tuple((m.T_map_marker, marker_corners(m.length)) for m in markers))


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


def reprojection_rms(T: np.ndarray, points: np.ndarray, pixels: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(P,) RMS residual length (pixels) of P poses ``T_camera_target`` (P, 4, 4), each scored on its (P, M, 3)
    target-frame points against (P, M, 2) undistorted pixels; inf where a point is behind the camera."""
    p = points @ T[:, :3, :3].transpose(0, 2, 1) + T[:, None, :3, 3]
    positive = p[..., 2] > 0
    residuals = p[..., :2] / np.where(positive, p[..., 2], 1.0)[..., None] @ K[:2, :2].T + K[:2, 2] - pixels
    return np.where(positive.all(axis=1), np.sqrt(np.sum(residuals**2, axis=(1, 2)) / points.shape[1]), np.inf)


def ippe_candidates(observations: Sequence[Observation], K: np.ndarray) -> list[list[Candidate] | None]:
    """Per observation (all of one point count), up to two ``T_camera_target`` candidates, lowest RMS
    first, every point in front of the camera; None when OpenCV's IPPE finds no pose.

    Coplanar points: OpenCV's two IPPE solutions (IPPE_SQUARE for one marker) in the plane
    frame. Otherwise each marker's IPPE_SQUARE solutions composed with ``T_target_marker^-1``,
    of which only the best over all points is kept.
    """
    rotations, translations, frames, owners = [], [], [], []
    coplanar: list[bool | None] = []
    for i, observation in enumerate(observations):
        try:
            solutions, flat = ippe_solutions(observation, K)
        except DegenerateError:
            coplanar.append(None)
            continue
        coplanar.append(flat)
        for rotvec, translation, T_target_frame in solutions:
            rotations.append(cv2.Rodrigues(rotvec)[0])
            translations.append(translation)
            frames.append(T_target_frame)
            owners.append(i)
    scored: list[list[Candidate]] = [[] for _ in observations]
    if owners:
        T_target_frame = np.array(frames)
        T = np.empty((len(owners), 4, 4))
        T[:, 3] = (0.0, 0.0, 0.0, 1.0)
        T[:, :3, :3] = np.array(rotations) @ T_target_frame[:, :3, :3].transpose(0, 2, 1)
        T[:, :3, 3] = np.reshape(translations, (-1, 3)) - (T[:, :3, :3] @ T_target_frame[:, :3, 3:])[..., 0]
        rms = reprojection_rms(T, np.array([observations[i].points for i in owners]),
                               np.array([observations[i].pixels for i in owners]), K).tolist()
        for k, i in enumerate(owners):
            if rms[k] != math.inf:
                scored[i].append(Candidate(T[k], rms[k]))
    return [None if flat is None else sorted(candidates, key=lambda c: c.rms_px)[:2 if flat else 1]
            for candidates, flat in zip(scored, coplanar, strict=True)]


def ippe_solutions(observation: Observation,
                   K: np.ndarray) -> tuple[list[tuple[np.ndarray, np.ndarray, np.ndarray]], bool]:
    """OpenCV's IPPE solutions for the observation as ``(rvec, tvec, T_target_frame)``: the pose
    ``T_camera_frame`` (rotation vector and translation, (3, 1) each) of the frame the points were
    solved in (their plane, or one marker's), and that frame (4, 4); and whether the points are
    coplanar. DegenerateError when OpenCV refuses the points."""
    if len(observation.markers) > 1 and (plane := plane_frame(observation)) is not None:
        return [(*solution, plane) for solution in solve_ippe(in_plane(observation, plane), observation.pixels, K,
                                                              cv2.SOLVEPNP_IPPE)], True
    solutions = []
    for n, (T_target_marker, corners) in enumerate(observation.markers):
        solutions += [(*solution, T_target_marker) for solution in solve_ippe(
            corners, observation.pixels[4 * n:4 * n + 4], K, cv2.SOLVEPNP_IPPE_SQUARE)]
    return solutions, len(observation.markers) == 1


def solve_ippe(points: np.ndarray, pixels: np.ndarray, K: np.ndarray,
               flags: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """``(rvec, tvec)`` solutions ((3, 1) each, ``T_camera_plane``) of cv2.solvePnPGeneric for (M, 3) plane
    points (z = 0); DegenerateError when OpenCV refuses the points."""
    try:
        _, rvecs, tvecs, _ = cv2.solvePnPGeneric(points, pixels, K, None, flags=flags)
    except cv2.error as error:
        raise DegenerateError(f"IPPE found no pose: {error.err}") from error
    return list(zip(rvecs, tvecs, strict=True))


def normals_at(T: np.ndarray, observations: list[Observation], K: np.ndarray) -> np.ndarray:
    """(P, 6, 6) ``J^T J`` of the residual Jacobian of P poses ``T_camera_target`` (P, 4, 4), each on its
    observation (all of one point count)."""
    _, J = residuals_and_jacobians(T, np.array([o.points for o in observations]),
                                   np.array([o.pixels for o in observations]), K)
    return J.transpose(0, 2, 1) @ J


def homography_pose(observation: Observation, T_target_plane: np.ndarray, K: np.ndarray) -> np.ndarray:
    """``T_camera_target`` from the normalised DLT homography of the coplanar points (DegenerateError if none)."""
    H = homography_dlt(in_plane(observation, T_target_plane)[:, :2], observation.pixels)
    return pose_from_homography(H, K) @ invert(T_target_plane)
