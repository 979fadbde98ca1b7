"""Map initialisation from two frames of one calibrated camera: a relative pose and 3D points, or the
reason to wait for a later frame.

Both an essential matrix and a homography are fitted to the matches by USAC (``two_view``). When
the homography explains the matches about as well as the essential matrix, the view is dominated by
a plane, or the camera only rotated: the homography is then the model that holds, and an essential
matrix fitted to it is ill-determined (on a plane seen with noise it came out several degrees
wrong). The two are compared as ORB-SLAM does: each match within a chi-square bound of a model
adds ``5.991 - chi2`` of both images to that model's support (``two_view.essential_support``,
``homography_support``; an epipolar distance has one degree of freedom, a transfer error two), and
the homography is taken when ``S_H / (S_H + S_E) > planar_ratio``. Counting inliers at one pixel
threshold instead does not work: a point-to-point transfer error exceeds a point-to-line distance
for the same noise, and on a plane the homography then won only two matches in three.

Low parallax is told first, from the fits' own poses, before anything costly: the parallax of a
match under a pose is the angle between its two rays (``two_view.ray_parallax_deg``: the angle
its triangulated point sees the baseline under, with no triangulation). When the chosen model has
``min_matches`` inliers or more and every pose the fits offer sees its inliers under a median
parallax below ``EARLY_FRACTION`` of ``min_parallax_deg`` (the essential matrix under the rotation of its decomposition
that brings the rays closer, each decomposition of the homography under its own), the pair is
``low_parallax`` with no pose, no triangulation and no spread measured: the full fit below checks
the parallax first, under one of those poses or pycolmap's refinement of the essential one, and on
such pairs ends in the same status. The homography's decompositions are there because a wrong
essential matrix can explain a near-planar view (a wall) as a rotation: on room frames 300 / 345,
in 2 of 16 noise draws, USAC's pose sees 0.5-0.7 deg where the refined pose sees 6-8 deg.

The chosen model's pose is used to triangulate the model's inliers. From the essential matrix, it
is ``cv2.recoverPose`` on USAC's matrix, or pycolmap's refined LO-RANSAC pose
(``two_view.fit_relative_pose``) when that is clearly better supported (``two_view.support_gain``):
USAC alone settles, in some draws facing a wall, on a model clearly less supported than the true
pose and degrees off.
From the homography, it is the decomposition of ``cv2.decomposeHomographyMat`` with the most points
in front of both cameras. It is accepted only with a median parallax (of the model's inliers under
the chosen pose) large enough for depth to be measured, enough points in front of both cameras and,
from a homography, a runner-up
decomposition with clearly fewer points in front: two decompositions explain a plane's matches
equally well, and when both put the points in front nothing in the pair tells them apart, so the
result is ``planar_wait`` rather than a guess. A later frame paired with the same first frame does:
the true decomposition's plane normal (in the first frame) is the same for every such pair, while
the other's follows the direction of the camera's translation. Given ``planes``, the two normals of
an earlier ambiguous pair, the decomposition whose normal stays within ``PLANE_KEPT_DEG`` of one of
them while the other's moved ``PLANE_MOVED_DEG`` or more is taken. An essential pose whose predicted
rotation standard deviation (``two_view.pose_std_deg``) exceeds ``max_rotation_std_deg`` is
``pose_uncertain``: a view nearly planar (a wall filling it with 10 % depth range) scores as a general
scene, but its matches leave the pose undetermined by a degree or more. Pure rotation and too short a baseline end in
``low_parallax``: a later frame, further away, may initialise.

Frames: the first frame's camera frame is the map's frame; ``T_second_first`` (4, 4) maps it into
the second frame's camera frame (OpenCV camera frames), its translation of unit norm (monocular
scale is arbitrary); ``points`` (N, 3) float64 are in the first camera's frame, in those units.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from services.geometry.camera import undistort_pixels
from services.slam.two_view import (
    Triangulated,
    essential_support,
    fit_essential,
    fit_homography,
    fit_relative_pose,
    homography_support,
    pose_from_essential,
    pose_std_deg,
    poses_from_homography,
    ray_parallax_deg,
    rotations_from_essential,
    support_gain,
    triangulate_pair,
)

EARLY_FRACTION = 0.5
"""A pair is told ``low_parallax`` before the full fit only when the fits' poses see less than this fraction of
the bound: USAC's essential matrix can see much less parallax than the refined pose the full fit uses
(0.83 deg against 1.23 deg on room frames 0 / 8 with 1 000 keypoints a frame, a pair over the 1 deg bound)."""

PLANE_KEPT_DEG = 5.0
"""The true plane's normal, from two pairs with one first frame, agrees within this (noise)."""
PLANE_MOVED_DEG = 20.0
"""The wrong decomposition's normal has followed the translation's direction by at least this much."""

__all__ = ["PLANE_KEPT_DEG", "PLANE_MOVED_DEG", "InitialisationStatus", "InitialisationModel", "InitialisationSettings",
           "TwoViewInitialisation", "initialise"]


class InitialisationStatus(StrEnum):
    """What two frames allow: a map, or why not yet (the tracker's ``Pose.reason`` while it initialises)."""

    INITIALISED = "initialised"
    TOO_FEW_MATCHES = "too_few_matches"
    """Fewer matches, or model inliers, than ``min_matches`` (or no model at all)."""
    LOW_PARALLAX = "low_parallax"
    """Median parallax under ``min_parallax_deg``: pure rotation or too short a baseline."""
    PLANAR_WAIT = "planar_wait"
    """A plane dominates and its homography's two best decompositions cannot be told apart."""
    POSE_UNCERTAIN = "pose_uncertain"
    """The essential pose's predicted rotation standard deviation exceeds ``max_rotation_std_deg``: the
    matches do not determine it (a view nearly planar, too few matches)."""
    FEW_IN_FRONT = "few_in_front"
    """Under ``min_in_front`` of the inliers triangulate in front of both cameras: the pose is wrong."""


class InitialisationModel(StrEnum):
    """Which model gave the pose."""

    NONE = "none"
    ESSENTIAL = "essential"
    HOMOGRAPHY = "homography"


class InitialisationSettings(BaseModel):
    """The thresholds of two-view initialisation (see the module docstring).

    ``planar_ratio`` 0.45 is ORB-SLAM's. ``max_rotation_std_deg``: two of them make the 1 deg an initial
    map may be off; the translation direction's is not bounded: at the shortest baselines that initialise
    it is 2 to 5 deg, and tracking, not the first pose, settles it."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    threshold_px: float = Field(default=1.0, gt=0, description="USAC inlier bound (epipolar distance, homography "
                                                               "transfer error), px")
    confidence: float = Field(default=0.999, gt=0, lt=1, description="USAC's confidence")
    sigma_px: float = Field(default=1.0, gt=0, description="the matches' pixel noise the models are scored with")
    min_matches: int = Field(default=50, ge=5, description="least matches and least model inliers")
    planar_ratio: float = Field(default=0.45, gt=0, lt=1, description="the homography is the model when its "
                                                                      "support exceeds this fraction of both "
                                                                      "supports")
    min_parallax_deg: float = Field(default=1.0, ge=0, description="least median triangulation angle, deg")
    min_in_front: float = Field(default=0.9, ge=0, le=1, description="least fraction of the inliers in front of "
                                                                     "both cameras")
    ambiguity_ratio: float = Field(default=0.75, ge=0, le=1, description="a homography decomposition is taken only "
                                                                         "when the second best has at most this "
                                                                         "fraction of its points in front")
    max_rms_px: float = Field(default=2.0, gt=0, description="largest reprojection error (RMS over both views) of "
                                                             "a kept point, px")
    max_rotation_std_deg: float = Field(default=0.5, gt=0, description="largest predicted standard deviation of an "
                                                                       "essential pose's rotation "
                                                                       "(two_view.pose_std_deg), deg")
    min_support_gain: float = Field(default=1.0, ge=0, description="pycolmap's pose replaces USAC's when its "
                                                                   "support is larger by more than this many "
                                                                   "standard deviations of the per-match "
                                                                   "differences")


@dataclass(frozen=True)
class TwoViewInitialisation:
    """The outcome for N matches.

    ``status``; ``model``; ``T_second_first`` (4, 4) float64, translation of unit norm (None when no
    pose was found or chosen, as in a ``low_parallax`` told before the full fit; given in the other
    waiting statuses when one was); ``inliers`` (N,) bool, the matches
    triangulated in front of both cameras within ``max_rms_px`` (all False unless initialised);
    ``points`` (N, 3) float64, first camera's frame, NaN where not an inlier; ``parallax_deg``
    median parallax of the model's inliers under its pose (``two_view.ray_parallax_deg``), degrees; for
    a ``low_parallax`` told before the full fit, the largest such median over the poses the fits
    offered (NaN when not measured); ``in_front`` fraction of the model's inliers in front of both
    cameras (0 when not triangulated); ``pose_std_deg`` the essential pose's predicted standard
    deviation (rotation, translation direction), degrees (NaN when not measured);
    ``essential_inliers`` / ``homography_inliers`` the two USAC inlier counts; ``plane_normals`` (2, 3)
    the unit plane normals (first frame) of the two decompositions a ``planar_wait`` could not tell apart
    ((0, 3) otherwise), for ``initialise``'s ``planes`` with a later frame.
    """

    status: InitialisationStatus
    model: InitialisationModel
    T_second_first: np.ndarray | None
    inliers: np.ndarray
    points: np.ndarray
    parallax_deg: float
    in_front: float
    pose_std_deg: tuple[float, float]
    essential_inliers: int
    homography_inliers: int
    plane_normals: np.ndarray

    @property
    def initialised(self) -> bool:
        return self.status is InitialisationStatus.INITIALISED


def initialise(pixels_first: np.ndarray, pixels_second: np.ndarray, K: np.ndarray, dist: np.ndarray,
               settings: InitialisationSettings | None = None,
               planes: np.ndarray | None = None) -> TwoViewInitialisation:
    """Try to start a map from N matches: ``pixels_first[i]`` (observed, distorted px) in the first
    frame and ``pixels_second[i]`` in the second, both (N, 2), one camera of (3, 3) ``K`` and
    plumb_bob ``dist`` (5,). Degenerate cases end in a waiting status, never in a map. ``planes``
    (2, 3): the ``plane_normals`` of an earlier ``planar_wait`` with the same first frame, if any."""
    s = settings or InitialisationSettings()
    first = undistort_pixels(pixels_first, K, dist)
    second = undistort_pixels(pixels_second, K, dist)
    n = len(first)
    wait = _Outcome(n)
    if n < s.min_matches:
        return wait.result(InitialisationStatus.TOO_FEW_MATCHES)
    E, essential_inliers = fit_essential(first, second, K, s.threshold_px, s.confidence)
    H, homography_inliers = fit_homography(first, second, s.threshold_px, s.confidence)
    wait.counts = int(essential_inliers.sum()), int(homography_inliers.sum())
    if E is None and H is None:
        return wait.result(InitialisationStatus.TOO_FEW_MATCHES)
    support_E = essential_support(E, K, first, second, s.sigma_px) if E is not None else 0.0
    support_H = homography_support(H, first, second, s.sigma_px) if H is not None else 0.0
    planar = E is None or support_H > s.planar_ratio * (support_H + support_E)
    wait.model = InitialisationModel.HOMOGRAPHY if planar else InitialisationModel.ESSENTIAL
    decompositions = poses_from_homography(H, K) if H is not None else []
    homography_poses = [T for T, _ in decompositions]
    model_inliers = homography_inliers if planar else essential_inliers
    if model_inliers.sum() >= s.min_matches:
        essential_rotations = rotations_from_essential(E) if E is not None else []
        largest = _largest_parallax_deg(essential_rotations, essential_inliers, homography_poses, homography_inliers,
                                        first, second, K, s.min_matches)
        if largest < EARLY_FRACTION * s.min_parallax_deg:
            wait.parallax = largest
            return wait.result(InitialisationStatus.LOW_PARALLAX)
    if not planar:
        assert E is not None
        T_usac = pose_from_essential(E, first, second, K, essential_inliers)
        T, model_inliers = _best_essential_pose(T_usac, essential_inliers, first, second, K, s)
    if model_inliers.sum() < s.min_matches:
        return wait.result(InitialisationStatus.TOO_FEW_MATCHES)
    a, b = first[model_inliers], second[model_inliers]
    ambiguous = uncertain = False
    if planar:
        T, found, ambiguous, wait.normals = _pick_homography_pose(decompositions, K, a, b, s.ambiguity_ratio, planes)
    else:
        found = triangulate_pair(K, T, a, b)
        wait.pose_std = pose_std_deg(T, K, a, b, s.sigma_px)
        uncertain = not wait.pose_std[0] <= s.max_rotation_std_deg
    wait.T = T
    wait.in_front = float(found.in_front.mean())
    wait.parallax = _median_parallax_deg(T[:3, :3], K, a, b)
    if wait.parallax < s.min_parallax_deg:
        return wait.result(InitialisationStatus.LOW_PARALLAX)
    if wait.in_front < s.min_in_front:
        return wait.result(InitialisationStatus.FEW_IN_FRONT)
    if ambiguous:
        return wait.result(InitialisationStatus.PLANAR_WAIT)
    if uncertain:
        return wait.result(InitialisationStatus.POSE_UNCERTAIN)
    kept = found.in_front & (found.rms_px <= s.max_rms_px)
    inliers = np.zeros(n, bool)
    inliers[np.flatnonzero(model_inliers)[kept]] = True
    points = np.full((n, 3), np.nan)
    points[inliers] = found.points[kept]
    return wait.result(InitialisationStatus.INITIALISED, inliers, points)


def _largest_parallax_deg(essential_rotations: list[np.ndarray], essential_inliers: np.ndarray,
                          homography_poses: list[np.ndarray], homography_inliers: np.ndarray, first: np.ndarray,
                          second: np.ndarray, K: np.ndarray, min_matches: int) -> float:
    """The largest median parallax, degrees, under which a pose the two fits offer sees its inliers
    of the matches ``first``, ``second`` (N, 2): the essential matrix over its inliers, under the one of
    its two ``essential_rotations`` (3, 3) that brings the rays closer, and each of the homography's
    decompositions ``homography_poses`` (4, 4) over its own inliers; a model with under ``min_matches``
    inliers is not counted (NaN when none is left). The other rotation of the essential matrix, its
    twisted pair, turns the rays apart by tens of degrees; at a short baseline the cheirality check
    can pick it (room frames 0 / 7: 92 deg). A wrong essential matrix can explain a near-planar view
    (a wall) as a rotation: the homography's decompositions then show the baseline."""
    medians = []
    if homography_inliers.sum() >= min_matches:
        a, b = first[homography_inliers], second[homography_inliers]
        medians += [_median_parallax_deg(T[:3, :3], K, a, b) for T in homography_poses]
    if essential_rotations and essential_inliers.sum() >= min_matches:
        a, b = first[essential_inliers], second[essential_inliers]
        medians.append(min(_median_parallax_deg(R, K, a, b) for R in essential_rotations))
    return max(medians, default=float("nan"))


def _median_parallax_deg(R_b_a: np.ndarray, K: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    """Median over the matches ``a``, ``b`` (N, 2) of the angle between their rays under the rotation
    ``R_b_a`` (3, 3) (``two_view.ray_parallax_deg``), degrees."""
    return float(np.median(ray_parallax_deg(R_b_a, K, a, b)))


def _best_essential_pose(T_usac: np.ndarray, essential_inliers: np.ndarray, first: np.ndarray, second: np.ndarray,
                         K: np.ndarray, s: InitialisationSettings) -> tuple[np.ndarray, np.ndarray]:
    """``(T_second_first, its inliers (N,) bool)``: ``T_usac``, the pose of USAC's essential matrix, or
    pycolmap's refined relative pose (``two_view.fit_relative_pose``) when its support over all
    matches is larger by more than ``min_support_gain`` standard deviations (``two_view.support_gain``)."""
    T, inliers = fit_relative_pose(first, second, K, s.threshold_px, s.confidence)
    if T is not None and support_gain(T_usac, T, K, first, second, s.sigma_px) > s.min_support_gain:
        return T, inliers
    return T_usac, essential_inliers


def _pick_homography_pose(decompositions: list[tuple[np.ndarray, np.ndarray]], K: np.ndarray, a: np.ndarray,
                          b: np.ndarray, ambiguity_ratio: float,
                          planes: np.ndarray | None) -> tuple[np.ndarray, Triangulated, bool, np.ndarray]:
    """``(T_b_a, its triangulation, ambiguous, the two best's normals (2, 3))``: of a homography's
    ``decompositions`` ((4, 4) pose, (3,) normal each), the one with the most of the matches ``a``, ``b``
    in front of both cameras; ambiguous when the runner-up has more than ``ambiguity_ratio`` as many in
    front, unless ``planes`` (an earlier ambiguous pair's normals) keep one normal and not the other."""
    scored = []
    for T, normal in decompositions:
        found = triangulate_pair(K, T, a, b)
        scored.append((int(found.in_front.sum()), T, found, normal))
    scored.sort(key=lambda item: item[0], reverse=True)
    if len(scored) < 2 or scored[1][0] <= ambiguity_ratio * scored[0][0]:
        return scored[0][1], scored[0][2], False, np.zeros((0, 3))
    normals = np.array([scored[0][3], scored[1][3]])
    kept = _kept_plane(normals, planes)
    if kept is None:
        return scored[0][1], scored[0][2], True, normals
    return scored[kept][1], scored[kept][2], False, np.zeros((0, 3))


def _kept_plane(normals: np.ndarray, planes: np.ndarray | None) -> int | None:
    """Which of two decompositions' unit ``normals`` (2, 3) stays within ``PLANE_KEPT_DEG`` of one of the
    earlier pair's ``planes`` (2, 3) while the other is ``PLANE_MOVED_DEG`` or more from both (a plane's
    normal up to sign); None when neither or both."""
    if planes is None or len(planes) == 0:
        return None
    angles = np.degrees(np.arccos(np.clip(np.abs(normals @ planes.T), 0.0, 1.0))).min(axis=1)
    for kept, moved in ((0, 1), (1, 0)):
        if angles[kept] <= PLANE_KEPT_DEG and angles[moved] >= PLANE_MOVED_DEG:
            return kept
    return None


class _Outcome:
    """What is known so far of one ``initialise`` call, made into its result once the status is known."""

    def __init__(self, n: int):
        self.n = n
        self.model = InitialisationModel.NONE
        self.T: np.ndarray | None = None
        self.counts = (0, 0)
        self.parallax = float("nan")
        self.in_front = 0.0
        self.pose_std = (float("nan"), float("nan"))
        self.normals = np.zeros((0, 3))

    def result(self, status: InitialisationStatus, inliers: np.ndarray | None = None,
               points: np.ndarray | None = None) -> TwoViewInitialisation:
        return TwoViewInitialisation(
            status=status, model=self.model, T_second_first=self.T,
            inliers=np.zeros(self.n, bool) if inliers is None else inliers,
            points=np.full((self.n, 3), np.nan) if points is None else points,
            parallax_deg=self.parallax, in_front=self.in_front, pose_std_deg=self.pose_std,
            essential_inliers=self.counts[0], homography_inliers=self.counts[1],
            plane_normals=self.normals if status is InitialisationStatus.PLANAR_WAIT else np.zeros((0, 3)))
