"""Recognition of an image target in one frame: matches, a robust homography, then the planar pose.

Steps, each of which may end the attempt with the status saying why:

1. Match the frame's descriptors to the target's, both k = 2 nearest neighbours and Lowe's ratio
   test (a match is kept when its distance is below ``ratio`` times the second-nearest's): binary
   descriptors through a FLANN locality-sensitive hashing index of the target's, built once (a
   brute-force Hamming search of a frame's 2000 ORB descriptors among a target's 5000 costs several
   times as long, for the same pose: docs/feature-targets.md), float ones through a FLANN
   k-d forest. With ``cross_check`` a match is also the frame keypoint the target keypoint itself
   matches best (an exact brute-force search).
2. Undistort the matched frame pixels (``cv2.undistortPoints`` back onto the same ``K``) and fit the
   homography target-image pixel -> undistorted frame pixel with OpenCV's USAC (MAGSAC++ by default,
   the fastest and most accurate variant measured for this job).
3. The pose ``T_camera_target`` of the homography's inliers, made as every target pose is
   (``services.estimation.targets.pose``): the best refined IPPE candidate, refined again without
   the points whose residual exceeds the homography threshold.
4. The homography given with the pose is fitted again, by least squares, to the points the pose
   rests on: the robust estimator's own depends on the order of the matches (its random samples),
   this one only on the inliers.
5. With ``refine`` and the frame's pixels at hand (``recognise_image``, or ``recognise`` given ``grey``),
   the inliers' target points are measured to a fraction of a pixel against the target drawn at that
   homography (``services.estimation.targets.measure``: Lucas-Kanade with a forward-backward check), the
   homography is fitted again to them (USAC_MAGSAC with ``refine_threshold_px``, then least squares)
   and the pose made again from them with that threshold. Keypoints place a target's points to about a
   pixel of their pyramid level; the measured points are several times closer. When too few points
   survive the measurement the keypoints' pose stands.
6. A pose is given only with at least ``min_inliers`` points and an RMS residual of at most
   ``max_rms_px``, with its 6x6 covariance over (tx, ty, tz, rx, ry, rz) (target frame, metres and
   radians), the per-axis pixel noise ``sigma_px`` estimated from the residuals when not given.

Frames are in OpenCV's camera frame; pixels put the centre of the top-left pixel at (0, 0).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from enum import StrEnum

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from services.estimation.targets.alignment import TargetAligner
from services.estimation.targets.features import Extractor, is_binary, make_extractor, to_grey
from services.estimation.targets.measure import MeasureOptions, refine_homography
from services.estimation.targets.pose import fit_covariance, fit_planar_pose
from services.estimation.targets.target import Target
from services.geometry.camera import undistort_image, undistort_pixels
from services.geometry.shapes import check_shape

__all__ = [
    "Recognition",
    "RecognitionOptions",
    "RecognitionStatus",
    "TargetRecognizer",
    "match_descriptors",
]

FLANN_KDTREE = 1
FLANN_TREES = 4
FLANN_CHECKS = 64
FLANN_LSH = 6
LSH_TABLES = 4
LSH_KEY_BITS = 12
LSH_PROBE_LEVEL = 1
"""The hashing index of binary descriptors: 4 tables of 12-bit keys, probing buckets one bit away too,
finds nearly all of the brute-force search's ratio-tested matches."""


class RecognitionStatus(StrEnum):
    """The outcome of recognising a target in a frame; every value but ``recognised`` says why there is no
    pose (the tracker's ``Pose.reason``)."""

    RECOGNISED = "recognised"
    NO_FEATURES = "no_features"
    """The frame has no keypoints (or descriptors of another kind than the target's)."""
    TOO_FEW_MATCHES = "too_few_matches"
    """Fewer matches passed the ratio test than a homography needs to be trusted (``min_inliers``)."""
    NO_HOMOGRAPHY = "no_homography"
    """The robust estimator found no homography."""
    TOO_FEW_INLIERS = "too_few_inliers"
    """Fewer than ``min_inliers`` matches agree with the homography or the pose."""
    NO_POSE = "no_pose"
    """No IPPE candidate puts every point in front of the camera, or no refinement converged."""
    REPROJECTION_TOO_HIGH = "reprojection_too_high"
    """The pose's RMS residual exceeds ``max_rms_px``."""


class RecognitionOptions(BaseModel):
    """How a target is recognised from scratch (see the module docstring).

    ``ratio`` 0.8 is Lowe's own value for SIFT; ORB's Hamming distances pass it alike. ``threshold_px`` 3:
    keypoints of coarse pyramid levels are placed to about a pixel. ``min_inliers`` 15: a frame without the
    target gives at most a handful of chance inliers (docs/feature-targets.md). ``max_rms_px`` 1.5: a true
    pose stays well under a pixel, a wrong one agreeing with 15 chance matches does not. ``index_above``: the
    hashing index is three times faster than brute force on a 5000-descriptor poster and finds 97 % of its
    matches; a smaller target is matched by exact Hamming brute force, which costs little there and misses no
    match a small target can ill spare. ``refine`` is off by default: refined, recognition alone is about as
    accurate as tracking, whose bar is to be at least as accurate (docs/accuracy.md)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    ratio: float = Field(default=0.8, gt=0, le=1, description="Lowe's ratio test of the matches")
    cross_check: bool = Field(default=False, description="keep only mutual best matches")
    method: int = Field(default=cv2.USAC_MAGSAC, description="the USAC flag of cv2.findHomography (cv2.USAC_*)")
    threshold_px: float = Field(default=3.0, gt=0, description="the homography's inlier threshold and the residual "
                                                               "beyond which a point leaves the pose, undistorted px")
    min_inliers: int = Field(default=15, ge=4, description="points a recognised pose needs")
    max_rms_px: float = Field(default=1.5, gt=0, description="largest reprojection RMS of a recognised pose, px")
    sigma_px: float | None = Field(default=None, gt=0, description="per-axis pixel noise of the covariance, px; "
                                                                   "default: estimated from the residuals")
    confidence: float = Field(default=0.999, gt=0, lt=1, description="the robust estimator's confidence")
    max_iterations: int = Field(default=2000, ge=1, description="the robust estimator's iterations at most")
    index_above: int = Field(default=2000, ge=0, description="a binary target with more descriptors than this is "
                                                             "matched through a hashing index, a smaller one by "
                                                             "brute force")
    refine: bool = Field(default=False, description="measure the inliers against the target image and fit the "
                                                    "homography and pose again on them")
    measure: MeasureOptions = Field(default=MeasureOptions(), description="Lucas-Kanade settings of refine's "
                                                                          "measurement")
    refine_threshold_px: float = Field(default=1.0, gt=0, description="refine: the refit's inlier threshold, "
                                                                      "undistorted px")
    refine_points: int = Field(default=100, ge=1, description="refine: inliers measured at most (evenly through "
                                                              "their order)")


@dataclass(frozen=True)
class Recognition:
    """One target in one frame.

    ``status``: ``recognised`` or why not; ``target``: its name; ``matches``: matches that passed the
    ratio test; ``inliers``: points the pose rests on. With a pose only (else None / empty):
    ``T_camera_target`` (4, 4); ``homography`` (3, 3) target-image pixel -> undistorted frame pixel;
    ``inlier_frame`` and ``inlier_target`` (M,) int, the inliers' indices into the frame's and the
    target's keypoints; ``inlier_pixels`` (M, 2) their undistorted frame pixels; ``rms_px`` the RMS
    residual length, undistorted pixels (also given for ``reprojection_too_high``); ``covariance``
    (6, 6) over (tx, ty, tz, rx, ry, rz), target frame, metres and radians.
    """

    status: RecognitionStatus
    target: str
    matches: int = 0
    inliers: int = 0
    T_camera_target: np.ndarray | None = None
    homography: np.ndarray | None = None
    inlier_frame: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    inlier_target: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    inlier_pixels: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    rms_px: float = math.nan
    covariance: np.ndarray | None = None

    @property
    def recognised(self) -> bool:
        return self.status is RecognitionStatus.RECOGNISED


def make_matcher(binary: bool, exact: bool = False) -> cv2.DescriptorMatcher:
    """With ``exact`` a brute-force search (Hamming distance for binary descriptors, L2 for float ones); else a
    FLANN hashing index for binary descriptors, a FLANN k-d forest for float ones."""
    if exact:
        return cv2.BFMatcher(cv2.NORM_HAMMING if binary else cv2.NORM_L2)
    if binary:
        return cv2.FlannBasedMatcher({"algorithm": FLANN_LSH, "table_number": LSH_TABLES, "key_size": LSH_KEY_BITS,
                                      "multi_probe_level": LSH_PROBE_LEVEL}, {"checks": FLANN_CHECKS})
    return cv2.FlannBasedMatcher({"algorithm": FLANN_KDTREE, "trees": FLANN_TREES}, {"checks": FLANN_CHECKS})


def match_descriptors(matcher: cv2.DescriptorMatcher, query: np.ndarray, train: np.ndarray, ratio: float,
                      cross_check: bool = False) -> np.ndarray:
    """(M, 2) int64 rows ``(query index, train index)`` of the matches of (Q, D) ``query`` descriptors
    among (T, D) ``train`` descriptors (the matcher's own trained set when it has one) passing the
    ratio test; with ``cross_check`` only those whose train descriptor's best query match is the same."""
    if len(query) < 2 or len(train) < 2:
        return np.zeros((0, 2), np.int64)
    trained = not matcher.empty()
    pairs = matcher.knnMatch(query, k=2) if trained else matcher.knnMatch(query, train, k=2)
    rows = [(m[0].queryIdx, m[0].trainIdx) for m in pairs
            if len(m) == 2 and m[0].distance < ratio * m[1].distance]
    matches = np.array(rows, np.int64).reshape(-1, 2)
    if cross_check and len(matches):
        back = make_matcher(is_binary(query), exact=True).match(train, query)
        best_query = np.full(len(train), -1, np.int64)
        best_query[[m.queryIdx for m in back]] = [m.trainIdx for m in back]
        matches = matches[best_query[matches[:, 1]] == matches[:, 0]]
    return matches


class TargetRecognizer:
    """Recognises one target in frames; holds the target's matcher, trained once."""

    def __init__(self, target: Target, options: RecognitionOptions | None = None):
        self.target = target
        self.options = options or RecognitionOptions()
        self.binary = is_binary(target.descriptors)
        small = len(target.descriptors) <= self.options.index_above
        self.matcher = make_matcher(self.binary, exact=self.binary and small)
        self.matcher.add([target.descriptors])
        self.matcher.train()
        self.target_pixels = target.keypoints.astype(np.float64)
        self.aligner = TargetAligner(target)

    def recognise_image(self, image: np.ndarray, K: np.ndarray, dist: np.ndarray | None = None,
                        extract: Extractor | None = None) -> Recognition:
        """``recognise`` on the keypoints of ``image`` ((H, W) or (H, W, 3) BGR, uint8 or uint16) found by
        ``extract`` (default: the target's own detector settings)."""
        grey = to_grey(image)
        points, descriptors = (extract or make_extractor(self.target.detector))(grey)
        return self.recognise(points, descriptors, K, dist, grey)

    def recognise(self, points: np.ndarray, descriptors: np.ndarray, K: np.ndarray,
                  dist: np.ndarray | None = None, grey: np.ndarray | None = None) -> Recognition:
        """The target in a frame with (N, 2) keypoint ``points`` (distorted pixels) and their (N, D)
        ``descriptors`` (of the target's kind), seen by the camera ``K`` (3, 3) with OpenCV distortion
        coefficients ``dist`` (None: none); ``grey``: the frame itself, (H, W) uint8, for the refinement
        (None: none)."""
        K = check_shape(K, "3,3", "K", np.float64)
        o, name = self.options, self.target.name
        descriptors = np.asarray(descriptors)
        if len(points) == 0 or is_binary(descriptors) != self.binary or descriptors.ndim != 2 \
                or descriptors.shape[1] != self.target.descriptors.shape[1]:
            return Recognition(RecognitionStatus.NO_FEATURES, name)
        matches = match_descriptors(self.matcher, descriptors, self.target.descriptors, o.ratio, o.cross_check)
        if len(matches) < o.min_inliers:
            return Recognition(RecognitionStatus.TOO_FEW_MATCHES, name, len(matches))
        frame_rows, target_rows = matches[:, 0], matches[:, 1]
        pixels = np.asarray(points, dtype=np.float64).reshape(-1, 2)[frame_rows]
        if dist is not None and np.any(dist):
            pixels = undistort_pixels(pixels, K, np.asarray(dist, dtype=np.float64))
        H, mask = cv2.findHomography(self.target_pixels[target_rows], pixels, o.method, o.threshold_px,
                                     maxIters=o.max_iterations, confidence=o.confidence)
        if H is None or mask is None:
            return Recognition(RecognitionStatus.NO_HOMOGRAPHY, name, len(matches))
        inliers = np.flatnonzero(mask.ravel())
        if len(inliers) < o.min_inliers:
            return Recognition(RecognitionStatus.TOO_FEW_INLIERS, name, len(matches), len(inliers))
        fit = fit_planar_pose(self.target.points[target_rows[inliers]], pixels[inliers], K, o.threshold_px)
        if fit is None:
            return Recognition(RecognitionStatus.NO_POSE, name, len(matches), len(inliers))
        inliers = inliers[fit.kept]
        if len(inliers) < o.min_inliers:
            return Recognition(RecognitionStatus.TOO_FEW_INLIERS, name, len(matches), len(inliers))
        if fit.rms_px > o.max_rms_px:
            return Recognition(RecognitionStatus.REPROJECTION_TOO_HIGH, name, len(matches), len(inliers),
                               rms_px=fit.rms_px)
        covariance = fit_covariance(fit, o.sigma_px)
        if covariance is None:
            return Recognition(RecognitionStatus.NO_POSE, name, len(matches), len(inliers))
        H, _ = cv2.findHomography(self.target_pixels[target_rows[inliers]], pixels[inliers], 0)
        found = Recognition(RecognitionStatus.RECOGNISED, name, len(matches), len(inliers), fit.T_camera_target, H,
                            frame_rows[inliers], target_rows[inliers], pixels[inliers], fit.rms_px, covariance)
        if not o.refine or grey is None:
            return found
        return self._refined(found, H, grey, K, dist) or found

    def _refined(self, found: Recognition, H: np.ndarray, grey: np.ndarray, K: np.ndarray,
                 dist: np.ndarray | None) -> Recognition | None:
        """``found`` with its (3, 3) homography ``H`` and pose made again from its inliers measured in the
        (H, W) uint8 frame ``grey`` (step 5 of the module's docstring); None when too few points survive."""
        o = self.options
        frame = grey if dist is None or not np.any(dist) else undistort_image(grey, K, dist)
        refined = refine_homography(self.aligner, frame, H, self.target_pixels[found.inlier_target], o.measure,
                                    o.refine_threshold_px, o.refine_points, o.min_inliers)
        if refined is None:
            return None
        rows = np.flatnonzero(refined.kept)
        fit = fit_planar_pose(self.target.points[found.inlier_target[rows]], refined.pixels[rows], K,
                              o.refine_threshold_px)
        if fit is None or fit.kept.sum() < o.min_inliers:
            return None
        covariance = fit_covariance(fit, o.sigma_px)
        if covariance is None:
            return None
        rows = rows[fit.kept]
        return Recognition(RecognitionStatus.RECOGNISED, found.target, found.matches, len(rows), fit.T_camera_target,
                           refined.homography, found.inlier_frame[rows], found.inlier_target[rows],
                           refined.pixels[rows], fit.rms_px, covariance)
