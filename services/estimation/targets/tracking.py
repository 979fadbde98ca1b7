"""Incremental tracking of an image target from frame to frame, falling back to recognition.

A ``TargetTracker`` owns one target's state from frame to frame. Every frame it returns a
``TargetPose`` whose state (a ``TrackingState``) says where the pose came from:

* ``tracking``: the points of the previous frame followed into this one. A constant-velocity model
  (``services.estimation.motion.ConstantVelocity``, with the camera frame in the role of its
  world and the target in that of its body) predicts ``T_camera_target`` at the frame's stamp; the
  tracked target points projected with that prediction (through the lens distortion) are the initial
  guesses of pyramidal Lucas-Kanade (``cv2.calcOpticalFlowPyrLK``, ``OPTFLOW_USE_INITIAL_FLOW``,
  coarse to fine over ``levels`` levels, a ``window_px`` window), so each point is searched around
  where the motion puts it. Every point is then tracked back from this frame to the previous one and
  kept only when it lands within ``forward_backward_px`` of where it started. The pose of the kept
  points is made as recognition makes it (``services.estimation.targets.pose``: IPPE, Levenberg-
  Marquardt, points beyond ``threshold_px`` dropped, covariance).
* ``recognised``: there were no points to follow (first frame, after a loss) or following them
  failed (fewer than ``min_points`` survived the check or the pose, or its RMS exceeded
  ``max_rms_px``), and recognition (``services.estimation.targets.recognition``) found the target.
* ``lost``: recognition did not find it either; ``reason`` is recognition's status.

Points are refilled from the target whenever fewer than ``refill_below`` are followed: the target's
keypoints (its own pyramid's, level-0 image pixels) are projected with the frame's pose, and those in
view, not yet followed and in a cell of a ``spacing_px`` grid that no followed point occupies join,
one per cell, up to ``max_points``, so the points stay spread over the visible target. After
recognition the points are seeded the same way from the recognised pose.

Several targets: one tracker per target. A frame's keypoints are needed only by trackers that fall
back to recognition; ``FrameFeatures`` extracts them on first use and hands the same arrays to every
such tracker of the frame (``track_targets`` does this for a list of trackers, one extraction per
detector setting). Frames are described with the target's own detector settings (``Target.detector``),
as recognition describes them.

Frames: ``T_camera_target`` (4, 4) maps the target frame (origin at the image's centre, x right, y
up, z towards the viewer) to OpenCV's camera frame. Tracked pixels are the frame's own (distorted)
pixels, the centre of the top-left pixel at (0, 0); poses and residuals use undistorted pixels.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from protocol.tracking_state import TrackingState
from services.detection.keypoints.detector import KeypointParams
from services.estimation.motion import DEFAULT_MOTION, ConstantVelocity, MotionOptions
from services.estimation.targets.alignment import AlignmentOptions, TargetAligner
from services.estimation.targets.features import Extractor, make_extractor, to_grey
from services.estimation.targets.measure import MeasureOptions, follow, measure_points
from services.estimation.targets.pose import fit_covariance, fit_planar_pose
from services.estimation.targets.recognition import RecognitionOptions, TargetRecognizer
from services.estimation.targets.target import Target
from services.geometry.camera import project_points, undistort_image, undistort_pixels
from services.geometry.shapes import check_shape

__all__ = [
    "FrameFeatures",
    "TargetPose",
    "TargetTracker",
    "TrackingOptions",
    "track_targets",
]

MIN_DEPTH_M = 1e-6


class TrackingOptions(BaseModel):
    """How a target is followed from frame to frame (see the module docstring).

    The defaults follow a target at 640x480 about three times as fast as 21 px windows, 400 points
    and measuring them every frame, as accurately (docs/feature-targets.md): the motion model's
    prediction leaves Lucas-Kanade little to search, and three levels keep the reach (about 50 px)
    of a prediction that is off."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    measure: MeasureOptions = Field(default=MeasureOptions(), description="Lucas-Kanade settings of following "
                                                                          "and measuring points")
    threshold_px: float = Field(default=2.0, gt=0, description="the residual beyond which a point leaves the pose, "
                                                               "undistorted px")
    min_points: int = Field(default=30, ge=4, description="points a tracked pose needs")
    max_rms_px: float = Field(default=1.0, gt=0, description="largest reprojection RMS of a tracked pose, px")
    max_points: int = Field(default=250, ge=4, description="points followed at most")
    refill_below: int = Field(default=150, ge=4, description="refill the points from the target when fewer are "
                                                             "followed")
    spacing_px: float = Field(default=16.0, gt=0, description="cell side of the refill grid, px")
    anchor_every: int = Field(default=2, ge=0, description="measure followed points afresh against the target "
                                                           "every this many tracked frames (0: never)")
    sigma_px: float | None = Field(default=None, gt=0, description="per-axis pixel noise of the covariance, px; "
                                                                   "default: estimated from the residuals")
    align: bool = Field(default=False, description="refine each pose by direct alignment of the target image (ECC)")
    alignment: AlignmentOptions = Field(default=AlignmentOptions(), description="the direct alignment's options")
    motion: MotionOptions = Field(default=DEFAULT_MOTION, description="the constant-velocity model's options")

    @model_validator(mode="after")
    def _point_counts(self) -> TrackingOptions:
        if not self.min_points <= self.refill_below <= self.max_points:
            raise ValueError(f"need min_points <= refill_below <= max_points, got {self.min_points}, "
                             f"{self.refill_below}, {self.max_points}")
        return self


@dataclass(frozen=True)
class TargetPose:
    """One target in one frame.

    ``state``: ``recognised``, ``tracking`` or ``lost``; ``target``: its name; ``reason``: why it is
    lost (recognition's status: ``too_few_matches``, ...), empty otherwise. With a pose only (else None /
    empty): ``T_camera_target`` (4, 4); ``inliers``: points the pose rests on; ``rms_px``: their RMS
    residual length, undistorted pixels; ``covariance`` (6, 6) over (tx, ty, tz, rx, ry, rz), target
    frame, metres and radians; ``points`` (M, 3) float64 target frame and ``pixels`` (M, 2) float32 the
    frame's own (distorted) pixels of the points followed on from this frame.
    """

    state: TrackingState
    target: str
    reason: str = ""
    T_camera_target: np.ndarray | None = None
    inliers: int = 0
    rms_px: float = math.nan
    covariance: np.ndarray | None = None
    points: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    pixels: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.float32))

    @property
    def posed(self) -> bool:
        return self.state is not TrackingState.LOST


class FrameFeatures:
    """The keypoints and descriptors of one (H, W) uint8 frame, extracted by ``extract`` on first use only."""

    def __init__(self, grey: np.ndarray, extract: Extractor):
        self.grey = grey
        self.extract = extract
        self._found: tuple[np.ndarray, np.ndarray] | None = None

    def get(self) -> tuple[np.ndarray, np.ndarray]:
        """``(points, descriptors)``: (N, 2) float32 pixels and (N, D) descriptors (``Extractor``'s)."""
        if self._found is None:
            self._found = self.extract(self.grey)
        return self._found


@dataclass(frozen=True)
class _Tracks:
    """Points followed into the next frame: (M,) target keypoint ``ids``, (M, 3) target ``points`` and
    (M, 2) float32 distorted ``pixels`` in the frame ``grey``, posed at ``T_camera_target``."""

    grey: np.ndarray
    ids: np.ndarray
    points: np.ndarray
    pixels: np.ndarray
    T_camera_target: np.ndarray


class TargetTracker:
    """Tracks one target through a stream of frames (see the module's docstring)."""

    def __init__(self, target: Target, options: TrackingOptions | None = None,
                 recognition: RecognitionOptions | None = None, extract: Extractor | None = None):
        self.target = target
        self.options = options or TrackingOptions()
        self.recognizer = TargetRecognizer(target, recognition)
        self.extract = extract or make_extractor(target.detector)
        self.aligner = TargetAligner(target, self.options.alignment)
        self.measuring = self.options.measure
        self.motion = ConstantVelocity(self.options.motion)
        self._tracks: _Tracks | None = None
        self._unanchored = 0
        self._candidates = np.unique(target.keypoints.astype(np.float64), axis=0, return_index=True)[1]

    @property
    def tracking(self) -> bool:
        """Whether the next frame starts from points followed from this one (else it needs recognition)."""
        return self._tracks is not None

    def reset(self) -> None:
        """Forget the followed points and the motion: the next frame is recognised."""
        self._tracks = None
        self.motion.reset()

    def track(self, image: np.ndarray, K: np.ndarray, dist: np.ndarray | None, stamp_ns: int,
              features: FrameFeatures | None = None) -> TargetPose:
        """The target in ``image`` ((H, W) or (H, W, 3) BGR, uint8 or uint16) taken at ``stamp_ns`` (after the
        previous frame's) by the camera ``K`` (3, 3) with OpenCV distortion ``dist`` (None: none).

        ``features``: the frame's shared keypoints, used when the frame needs recognition (default:
        extracted here on demand).
        """
        K = check_shape(K, "3,3", "K", np.float64)
        dist = None if dist is None or not np.any(dist) else np.asarray(dist, dtype=np.float64)
        grey = features.grey if features is not None else to_grey(image)
        if self._tracks is not None:
            tracked = self._follow(self._tracks, grey, K, dist, stamp_ns)
            if tracked is not None:
                return tracked
        self.reset()
        points, descriptors = (features or FrameFeatures(grey, self.extract)).get()
        found = self.recognizer.recognise(points, descriptors, K, dist, grey)
        if not found.recognised or found.T_camera_target is None:
            return TargetPose(TrackingState.LOST, self.target.name, found.status.value)
        T = self._aligned(grey, K, dist, found.T_camera_target)
        self.motion.update(stamp_ns, T)
        tracks = self._refill(_Tracks(grey, *_no_points(), T), K, dist)
        self._tracks = tracks
        return TargetPose(TrackingState.RECOGNISED, self.target.name, "", T, found.inliers, found.rms_px,
                          found.covariance, tracks.points, tracks.pixels)

    def _follow(self, tracks: _Tracks, grey: np.ndarray, K: np.ndarray, dist: np.ndarray | None,
                stamp_ns: int) -> TargetPose | None:
        """The pose from the points of ``tracks`` followed into ``grey``; None when the check or the pose fails."""
        o = self.options
        predicted = self.motion.predict(stamp_ns)
        T_guess = tracks.T_camera_target if predicted is None else predicted.T_world_body
        guesses, visible = _project(tracks.points, T_guess, K, dist, grey.shape, 0.0)
        if visible.sum() < o.min_points:
            return None
        ids, points, start = tracks.ids[visible], tracks.points[visible], tracks.pixels[visible]
        forward, kept = follow(tracks.grey, grey, start, guesses[visible], self.measuring)
        if kept.sum() < o.min_points:
            return None
        pixels = forward[kept]
        undistorted = pixels.astype(np.float64) if dist is None else undistort_pixels(pixels, K, dist)
        fit = fit_planar_pose(points[kept], undistorted, K, o.threshold_px)
        if fit is None or fit.kept.sum() < o.min_points or fit.rms_px > o.max_rms_px:
            return None
        covariance = fit_covariance(fit, o.sigma_px)
        if covariance is None:
            return None
        T = self._aligned(grey, K, dist, fit.T_camera_target)
        self.motion.update(stamp_ns, T)
        followed = _Tracks(grey, ids[kept][fit.kept], points[kept][fit.kept], pixels[fit.kept], T)
        self._unanchored += 1
        if o.anchor_every and self._unanchored >= o.anchor_every:
            followed = self._refill(_Tracks(grey, *_no_points(), T), K, dist)
        elif len(followed.ids) < o.refill_below:
            followed = self._refill(followed, K, dist)
        self._tracks = followed
        return TargetPose(TrackingState.TRACKING, self.target.name, "", T, int(fit.kept.sum()), fit.rms_px, covariance,
                          followed.points, followed.pixels)

    def _aligned(self, grey: np.ndarray, K: np.ndarray, dist: np.ndarray | None, T: np.ndarray) -> np.ndarray:
        """``T`` refined by direct alignment when the options ask for it and it succeeds, else ``T``."""
        if not self.options.align:
            return T
        refined = self.aligner.refine(grey, K, dist, T)
        return T if refined is None else refined

    def _refill(self, tracks: _Tracks, K: np.ndarray, dist: np.ndarray | None) -> _Tracks:
        """``tracks`` with target keypoints projected at its pose joining, one per free grid cell, up to
        ``max_points``."""
        o = self.options
        if not len(tracks.ids):
            self._unanchored = 0
        candidates = np.setdiff1d(self._candidates, tracks.ids, assume_unique=True)
        points = self.target.points[candidates]
        margin = o.measure.window_px / 2
        pixels, visible = _project(points, tracks.T_camera_target, K, dist, tracks.grey.shape, margin)
        cells = np.floor(pixels / o.spacing_px).astype(np.int64)
        width = int(tracks.grey.shape[1] / o.spacing_px) + 2
        keys = cells[:, 1] * width + cells[:, 0]
        taken = np.floor(tracks.pixels / o.spacing_px).astype(np.int64)
        occupied = taken[:, 1] * width + taken[:, 0]
        free = visible & ~np.isin(keys, occupied)
        rows = np.flatnonzero(free)
        _, first = np.unique(keys[rows], return_index=True)
        chosen = rows[np.sort(first)][: max(o.max_points - len(tracks.ids), 0)]
        placed, found = self._place(tracks.grey, K, dist, tracks.T_camera_target, candidates[chosen])
        chosen = chosen[found]
        return _Tracks(tracks.grey, np.concatenate([tracks.ids, candidates[chosen]]),
                       np.concatenate([tracks.points, points[chosen]]),
                       np.concatenate([tracks.pixels, placed[found]]), tracks.T_camera_target)

    def _place(self, grey: np.ndarray, K: np.ndarray, dist: np.ndarray | None, T_camera_target: np.ndarray,
               ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(pixels, found)``: (M, 2) float32 distorted pixels in ``grey`` of the target keypoints ``ids`` (M,),
        measured against the target drawn at ``T_camera_target`` (``services.estimation.targets.measure``), each
        starting where the pose projects it; (M,) bool, measured."""
        frame = grey if dist is None else undistort_image(grey, K, dist)
        H = self.aligner.homography(K, T_camera_target)
        moved, found = measure_points(self.aligner, frame, H, self.target.keypoints[ids], self.measuring)
        if dist is not None:
            rays = np.column_stack([moved, np.ones(len(moved))]) @ np.linalg.inv(K).T
            moved = project_points(rays, K, dist).astype(np.float32)
        return moved, found


def _no_points() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Empty (0,) ids, (0, 3) points and (0, 2) float32 pixels."""
    return np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 2), np.float32)


def _project(points: np.ndarray, T_camera_target: np.ndarray, K: np.ndarray, dist: np.ndarray | None,
             shape: tuple[int, ...], margin_px: float) -> tuple[np.ndarray, np.ndarray]:
    """``(pixels, visible)``: (M, 2) float32 distorted pixels of (M, 3) target ``points`` at ``T_camera_target``
    and (M,) bool, in front of the camera, on the side of the target it faces and at least ``margin_px``
    inside an image of ``shape`` (H, W)."""
    points_cam = points @ T_camera_target[:3, :3].T + T_camera_target[:3, 3]
    front = points_cam[:, 2] > MIN_DEPTH_M
    facing = float(T_camera_target[:3, 2] @ T_camera_target[:3, 3]) < 0
    pixels = np.zeros((len(points), 2), np.float32)
    if front.any():
        pixels[front] = project_points(points_cam[front], K, dist)
    h, w = shape[:2]
    inside = (pixels[:, 0] >= margin_px) & (pixels[:, 0] <= w - 1 - margin_px) \
        & (pixels[:, 1] >= margin_px) & (pixels[:, 1] <= h - 1 - margin_px)
    return pixels, front & inside & facing


def track_targets(trackers: Sequence[TargetTracker], image: np.ndarray, K: np.ndarray, dist: np.ndarray | None,
                  stamp_ns: int) -> list[TargetPose]:
    """Every tracker's ``TargetPose`` in one frame, in order; the frame is converted to grey once and its
    keypoints extracted at most once per detector setting, only when a tracker needs recognition."""
    grey = to_grey(image)
    shared: dict[KeypointParams, FrameFeatures] = {}
    poses = []
    for tracker in trackers:
        features = shared.setdefault(tracker.target.detector, FrameFeatures(grey, tracker.extract))
        poses.append(tracker.track(grey, K, dist, stamp_ns, features))
    return poses
