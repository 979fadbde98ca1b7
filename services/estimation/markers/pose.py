"""Planar-marker poses of one camera, frame after frame: ``T_camera_marker`` and ``T_camera_<map>``.

Input per frame: detected marker ids, their corners in distorted pixels (ArUco order TL, TR,
BR, BL), side lengths and the calibration. The corners are undistorted once
(``cv2.undistortPoints(..., P=K)``); everything after works on a distortion-free pinhole.

The estimator composes three parts: planar PnP (``services.geometry.planar_pnp``: IPPE
candidates, homography pose, scoring), the choice between the two planar candidates
(``services.estimation.markers.ambiguity``) and Levenberg-Marquardt refinement with covariances
(``services.geometry.refine``). Marker maps come from ``services.estimation.markers.map``.

Methods (``method``):

* ``"lm"``: normalised DLT homography of the corners, pose from the homography, then
  Levenberg-Marquardt on the reprojection error; it starts from the best IPPE candidate
  instead when the homography pose puts a corner behind the camera.
* ``"ippe"``: OpenCV's IPPE_SQUARE (``cv2.solvePnPGeneric``) alone.
* ``"ippe+lm"`` (default): the IPPE candidate refined by the same LM. It reaches the same optimum
  as ``lm`` from a closer start and needs no homography per marker, so it is the cheaper of the two.

Accuracy of each method: docs/benchmarks.md.

The single markers of a frame are solved together: each still gets its own OpenCV IPPE call,
but the candidates of all of them are scored in one batch, their LM refinements run as one
``refine_poses`` batch (each problem advancing exactly as it would alone) and their covariances
come from one call on the LM's ``J^T J``; the map is a second batch. Each marker's pose is
exactly the one it gets alone.

Planar ambiguity: both IPPE candidates are always computed; ``AmbiguityTracker`` flags the pose
``ambiguous`` and picks between them (``ambiguity_ratio``, ``prior_max_age``). The refined
methods refine both candidates when the pose is ambiguous (dropping one that does not
converge), only one otherwise.

Marker maps (``marker_map``): the map's pose ``T_camera_<name>`` comes from all visible corners of
its markers at once. Its candidates are OpenCV's IPPE (and, for ``lm``, the homography) on all
corners when the visible corners are coplanar; otherwise each visible marker's IPPE_SQUARE
candidates composed with ``T_map_marker^-1``, of which the lowest RMS over all corners is kept.
The same ambiguity test and LM follow. A map's markers get no pose of their own (the map's pose
and ``T_map_marker`` give it), and their side lengths come from the map, not the detections.

Failures give no pose, never an exception; they are counted per marker or map by ``SkipReason``.

Poses carry the RMS of the corner residual lengths (undistorted pixels), the number of corners
used, the ambiguity flag and the 6x6 covariance ``refine.pose_covariances`` gives for independent
Gaussian corner noise of ``corner_sigma_px`` per axis (default 0.5 px, the noise model of the
accuracy tests).
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass
from enum import StrEnum
from typing import Literal, get_args

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from services.estimation.markers.ambiguity import AmbiguityTracker
from services.estimation.markers.map import MarkerMap, marker_corners
from services.geometry.camera import UNDISTORT_CRITERIA
from services.geometry.homography import DegenerateError
from services.geometry.planar_pnp import (
    Candidate,
    Patch,
    PlanarView,
    homography_pose,
    ippe_candidates,
    normals_at,
    plane_frame,
    reprojection_rms,
)
from services.geometry.refine import pose_covariances, refine_poses
from services.geometry.shapes import check_shape

Method = Literal["lm", "ippe", "ippe+lm"]
METHODS: tuple[Method, ...] = get_args(Method)
DEFAULT_METHOD: Method = "ippe+lm"
MIN_TURN = 1e-6
"""A quadrilateral's turn at each corner (edge cross product) must exceed this fraction of its mean squared edge."""
NEXT_CORNER = np.array([1, 2, 3, 0])
IDENTITY = np.eye(4)
IDENTITY.flags.writeable = False


class SkipReason(StrEnum):
    """Why a marker or map got no pose in a frame; the values are the counters' and reports' kinds."""

    NO_SIDE_LENGTH = "no_side_length"
    """Side length <= 0 or not finite."""
    DUPLICATE_ID = "duplicate_id"
    """The id was detected more than once in the frame."""
    DEGENERATE_CORNERS = "degenerate_corners"
    """Not finite, coincident, collinear, zero-area, non-convex or mirrored quadrilateral."""
    DEGENERATE_HOMOGRAPHY = "degenerate_homography"
    """The DLT or OpenCV's IPPE finds no homography."""
    BEHIND_CAMERA = "behind_camera"
    """No candidate has every corner in front of the camera."""
    NOT_CONVERGED = "not_converged"
    """No LM refinement converged within the iteration limit."""
    ILL_CONDITIONED = "ill_conditioned"
    """The corners leave the pose undetermined."""


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
    failures: Counter[SkipReason]


@dataclass(frozen=True)
class Observation(PlanarView):
    """A target's planar view (one square patch per visible marker, ``T_target_marker`` and its (4, 3)
    corners) with the target's name and its visible markers' ids."""

    target: str
    marker_ids: tuple[int, ...]


class MarkerPoseOptions(BaseModel):
    """How ``MarkerPoseEstimator`` makes poses (see the module docstring)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    method: Method = Field(default=DEFAULT_METHOD, description="lm (homography, then Levenberg-Marquardt), ippe "
                                                               "(OpenCV's IPPE_SQUARE) or ippe+lm (IPPE refined "
                                                               "by Levenberg-Marquardt)")
    corner_sigma_px: float = Field(default=0.5, gt=0, description="corner noise assumed by the covariance, px")
    ambiguity_ratio: float = Field(default=2.0, ge=1, description="a pose is ambiguous when the other planar "
                                                                  "candidate's error is within this factor of its "
                                                                  "own")
    prior_max_age: int = Field(default=5, ge=0, description="frames a target's last pose is kept to choose "
                                                            "between its candidates")
    max_iterations: int = Field(default=100, ge=1, description="Levenberg-Marquardt iterations at most")


class MarkerPoseEstimator:
    """Marker and marker-map poses of one camera; keeps each target's last pose to resolve ambiguities.

    ``options`` may be replaced between frames (a live change of ``corner_sigma_px``, say); the ambiguity
    tracker keeps the ``ambiguity_ratio`` and ``prior_max_age`` it was made with."""

    def __init__(self, options: MarkerPoseOptions | None = None, marker_map: MarkerMap | None = None):
        self.options = options or MarkerPoseOptions()
        self.marker_map = marker_map
        self.ambiguity = AmbiguityTracker(self.options.ambiguity_ratio, self.options.prior_max_age)

    def reset(self) -> None:
        """Forget every target's previous pose."""
        self.ambiguity.reset()

    def estimate(self, ids: Sequence[int] | np.ndarray, corners: np.ndarray,
                 side_lengths: Sequence[float] | np.ndarray | float,
                 K: np.ndarray, dist: np.ndarray | None = None) -> FrameEstimate:
        """Poses of one frame.

        ``ids``: (N,) int; ``corners``: (N, 4, 2) float distorted pixels, ArUco order TL, TR, BR, BL;
        ``side_lengths``: (N,) metres (or one number for all; 0 = unknown); ``K``: (3, 3);
        ``dist``: OpenCV distortion coefficients or None.
        """
        K = check_shape(K, "3,3", "K", np.float64)
        self.ambiguity.next_frame()
        ids = np.asarray(ids, dtype=np.int64).reshape(-1)
        corners = np.asarray(corners, dtype=np.float64).reshape(len(ids), 4, 2)
        sides = (np.zeros(len(ids)) + np.asarray(side_lengths, dtype=np.float64)).tolist()
        failures: Counter[SkipReason] = Counter()
        counts = Counter(ids.tolist())
        finite = np.all(np.isfinite(corners), axis=(1, 2))
        if not finite.all():
            corners = np.where(finite[:, None, None], corners, 0.0)
        undistorted = undistort(corners, K, dist)
        valid = (finite & quadrilaterals_are_valid(undistorted)).tolist()
        in_map = self.marker_map.markers if self.marker_map else {}
        singles, map_rows = [], []
        for n, marker_id in enumerate(ids.tolist()):
            if counts[marker_id] > 1:
                failures[SkipReason.DUPLICATE_ID] += 1
            elif not valid[n]:
                failures[SkipReason.DEGENERATE_CORNERS] += 1
            elif marker_id in in_map:
                map_rows.append(n)
            elif not (math.isfinite(sides[n]) and sides[n] > 0):
                failures[SkipReason.NO_SIDE_LENGTH] += 1
            else:
                singles.append(single_observation(marker_id, sides[n], undistorted[n]))
        groups = [singles]
        if map_rows and self.marker_map is not None:
            groups.append([map_observation(self.marker_map, ids[map_rows], undistorted[map_rows])])
        poses = []
        for group in groups:
            for pose in self._solve(group, K):
                if isinstance(pose, SkipReason):
                    failures[pose] += 1
                else:
                    poses.append(pose)
        return FrameEstimate(poses, failures)

    def _solve(self, observations: list[Observation], K: np.ndarray) -> list[TargetPose | SkipReason]:
        """Per observation (all of one point count, solved together), its target's pose or the reason it
        has none; records each pose as its target's track."""
        if not observations:
            return []
        reasons: dict[int, SkipReason] = {}
        found: dict[int, list[Candidate]] = {}
        ambiguous: dict[int, bool] = {}
        for i, candidates in enumerate(ippe_candidates(observations, K)):
            if candidates is None:
                reasons[i] = SkipReason.DEGENERATE_HOMOGRAPHY
            elif not candidates:
                reasons[i] = SkipReason.BEHIND_CAMERA
            else:
                ambiguous[i] = self.ambiguity.is_ambiguous(candidates)
                found[i] = candidates if ambiguous[i] else candidates[:1]
        if self.options.method != "ippe":
            found = self._refine(observations, found, ambiguous, K, reasons)
        chosen = {i: self.ambiguity.choose(observations[i].target, candidates, ambiguous[i])
                  for i, candidates in found.items()}
        if not chosen:
            return [reasons[i] for i in range(len(observations))]
        picked = [candidate for candidate, _ in chosen.values()]
        if self.options.method == "ippe":
            normals = normals_at(np.array([c.T for c in picked]), [observations[i] for i in chosen], K)
        else:
            normals = np.array([c.normal for c in picked])
        covariances, regular = pose_covariances(normals, self.options.corner_sigma_px)
        poses: dict[int, TargetPose] = {}
        for k, (i, (candidate, anchored)) in enumerate(chosen.items()):
            observation = observations[i]
            if not regular[k]:
                reasons[i] = SkipReason.ILL_CONDITIONED
                continue
            self.ambiguity.record(observation.target, candidate.T, anchored)
            poses[i] = TargetPose(observation.target, candidate.T, candidate.rms_px, len(observation.points),
                                  ambiguous[i], covariances[k], observation.marker_ids)
        return [poses[i] if i in poses else reasons[i] for i in range(len(observations))]

    def _refine(self, observations: list[Observation], found: dict[int, list[Candidate]], ambiguous: dict[int, bool],
                K: np.ndarray, reasons: dict[int, SkipReason]) -> dict[int, list[Candidate]]:
        """The converged LM refinements of each observation's candidates (for ``lm`` and an unambiguous
        view, of its homography pose instead when that has every point in front), all run at once;
        an observation that gets none has its reason added to ``reasons``."""
        starts: list[tuple[int, np.ndarray]] = []
        for i, candidates in found.items():
            observation = observations[i]
            if self.options.method == "lm" and not ambiguous[i] and (plane := plane_frame(observation)) is not None:
                try:
                    T_homography = homography_pose(observation, plane, K)
                except DegenerateError:
                    reasons[i] = SkipReason.DEGENERATE_HOMOGRAPHY
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
                              np.array([observations[i].pixels for i in rows]), K, self.options.max_iterations)
        refined: dict[int, list[Candidate]] = {}
        for k, i in enumerate(rows):
            if result.degenerate[k]:
                reasons[i] = SkipReason.ILL_CONDITIONED
            elif result.converged[k]:
                refined.setdefault(i, []).append(Candidate(result.T[k], float(result.rms_px[k]), result.normal[k]))
        for i in rows:
            if i not in refined:
                reasons.setdefault(i, SkipReason.NOT_CONVERGED)
        return {i: candidates for i, candidates in refined.items() if i not in reasons}


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


def marker_patch(T_target_marker: np.ndarray, length: float) -> Patch:
    """A marker of side ``length`` (metres) at ``T_target_marker`` (4, 4) as a square patch."""
    return Patch(T_target_marker, marker_corners(length), square=True)


def single_observation(marker_id: int, length: float, pixels: np.ndarray) -> Observation:
    """The observation of one marker on its own (target ``marker/<id>``, target frame = marker frame)
    from its (4, 2) undistorted corner ``pixels``."""
    patch = marker_patch(IDENTITY, length)
    return Observation(patch.points, pixels, (patch,), f"marker/{marker_id}", (marker_id,))


def map_observation(marker_map: MarkerMap, ids: np.ndarray, pixels: np.ndarray) -> Observation:
    """The observation of a map from its visible markers' ``ids`` (K,) and (K, 4, 2) undistorted ``pixels``."""
    markers = [marker_map.markers[int(i)] for i in ids]
    return Observation(np.concatenate([m.corners() for m in markers]), pixels.reshape(-1, 2),
                       tuple(marker_patch(m.T_map_marker, m.length) for m in markers), marker_map.name,
                       tuple(int(i) for i in ids))
