"""Metric scale and a world anchor for monocular SLAM from a marker of known size.

Monocular SLAM poses ``T_map_camera`` are in a map frame of arbitrary origin, orientation and
scale. A marker of known side, seen in the same frames, gives metric ``T_camera_marker``
(``services.estimation.markers.pose``). From such pairs ``MarkerAnchor`` fits the similarity
``p_marker = s R p_map + t`` (``s``: metres per map unit), so that any SLAM pose can be given in
the marker's frame, in metres: ``T_marker_camera = S T_map_camera`` with the translation scaled
(``Anchor.to_marker``).

Which pairs count (``AnchorSettings``):

* a marker pose flagged ambiguous (the other planar solution explains the corners almost as well)
  is refused, as is one with a corner residual RMS over ``max_rms_px``, and one whose predicted
  position uncertainty (the pose covariance's translation block) exceeds ``max_relative_std`` of
  the marker's distance: the marker is far, or seen at a grazing angle;
* consistency: in every fit, a pair whose marker orientation in the map (``R_map_camera
  R_camera_marker``) is more than ``max_rotation_deg`` from the fitted one, or whose position
  residual exceeds ``outlier_factor`` times the median residual (and ``min_outlier_m``), is an
  outlier and left out of the fit (a wrong but unflagged planar solution, a SLAM pose gone astray).
  The first fit, over the pairs within ``max_rotation_deg`` of the robust mean orientation, is
  redone over the half of them with the smallest residuals before that test, so that a minority of
  outliers cannot drag it. Outliers are found again in every fit.

Two fits (``method``):

* ``"rays"`` (default): the marker's pose in the map frame, estimated from every frame and
  averaged. Each frame's rotation ``R_map_camera R_camera_marker`` is one estimate of the marker's
  orientation in the map; their robust mean (the chordal mean, ``scipy.spatial.transform.Rotation.mean``,
  over the pairs left after trimming to the closest half and then to ``max_rotation_deg``) is the
  anchor's rotation. The scale is not observable from one frame; the marker's origin and the scale
  are solved together from every frame's ``s o - s c_map = R_map_camera t_camera_marker`` (the camera
  centre plus the marker's metric offset must land on the same point), linear in ``(s o, s)``, by
  least squares with each frame's equations whitened by the covariance of the marker's position
  (from the pose covariance, plus ``pose_std_m`` for the SLAM pose): a triangulation of the
  marker's centre whose scale is the unknown. It uses the part of a marker pose that is precise,
  the marker's position in the camera: its bearing to a fraction of a pixel, its distance to a
  fraction of a percent; not its orientation, whose error (a degree or more for a marker 50 px
  wide) turns into centimetres on the camera centre at a few metres' distance. Any baseline
  serves, towards the marker (the distances change) or across (the bearings change).
* ``"centres"``: Umeyama's closed form with scale (``geometry.absolute_orientation.umeyama_alignment``)
  between the camera centres in the map and in the marker frame (``-R_camera_marker^T t_camera_marker``).
  Simple and standard, but each metric centre carries the marker's orientation error times the
  distance, and the rotation comes from the shape of the path alone (it needs a path that is not
  a straight line: ``min_breadth_m``).

``tests/unit/test_slam_anchor.py`` compares the two on the same noisy sightings of an exact path:
``rays`` is the more accurate in scale, rotation and position. With a real SLAM trajectory
(``tests/accuracy/test_slam_anchor.py``; figures of both in docs/slam.md) ``centres`` lands its camera
centres a little closer (it minimises just that) but its rotation is further off, so the marker's
origin, seen from the camera, lands further away: where an AR app draws. ``rays`` is the default.

Refitting: the fit is redone after every accepted pair, over the last ``max_frames`` accepted
pairs; it is never frozen. Monocular scale drifts along a sequence, so the newest sightings say
best how the map around the marker relates to metres. An
anchor is reported once the inliers number ``min_frames`` and their camera centres, the SLAM ones
carried into the marker frame by the fit (more precise than the marker poses'), spread over
``min_baseline_m`` (twice their RMS distance from their mean: two places ``b`` apart give ``b``);
for ``centres`` also across their main direction over ``min_breadth_m`` (twice their RMS distance
from their best line).

All frames are OpenCV camera frames and ArUco marker frames (x right, y up, z out of the marker);
``T_a_b`` maps b coordinates into a.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from enum import StrEnum
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator
from scipy.spatial.transform import Rotation

from services.geometry.absolute_orientation import umeyama_alignment
from services.geometry.evaluation import Similarity, apply_similarity
from services.geometry.shapes import check_shape

__all__ = ["Anchor", "AnchorMethod", "AnchorSettings", "AnchorStatus", "MarkerAnchor", "MarkerSighting", "Refusal"]

AnchorMethod = Literal["rays", "centres"]


class AnchorSettings(BaseModel):
    """Thresholds of ``MarkerAnchor`` (see the module docstring); none depends on the sequence."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    method: AnchorMethod = Field(default="rays", description="rays (the marker's position from every frame, "
                                                             "averaged) or centres (Umeyama on the camera centres)")
    max_rms_px: float = Field(default=1.0, gt=0, description="largest corner residual RMS of a sighting, px")
    max_relative_std: float = Field(default=0.03, gt=0, description="largest predicted position error of a "
                                                                    "sighting, as a share of the marker's distance")
    max_rotation_deg: float = Field(default=5.0, gt=0, description="largest angle between a sighting's marker "
                                                                   "orientation and the fit's, deg")
    outlier_factor: float = Field(default=4.0, gt=0, description="a sighting whose residual exceeds this many "
                                                                 "median residuals is an outlier")
    min_outlier_m: float = Field(default=0.02, gt=0, description="least residual of an outlier, m")
    pose_std_m: float = Field(default=0.005, gt=0, description="standard deviation of a SLAM pose's position, "
                                                               "m (map units scaled)")
    min_frames: int = Field(default=20, ge=3, description="inliers an anchor needs")
    min_baseline_m: float = Field(default=0.3, ge=0, description="least spread of the inliers' camera centres, m")
    min_breadth_m: float = Field(default=0.2, ge=0, description="centres: least spread of the camera centres "
                                                                "across their main direction, m")
    max_frames: int = Field(default=900, ge=3, description="newest accepted sightings each fit is made over")

    @model_validator(mode="after")
    def _a_frame_range(self) -> AnchorSettings:
        if self.min_frames > self.max_frames:
            raise ValueError(f"need min_frames <= max_frames, got {self.min_frames} and {self.max_frames}")
        return self


@dataclass(frozen=True)
class MarkerSighting:
    """One marker pose as the marker estimator gives it: ``T_camera_marker`` (4, 4), metres;
    ``rms_px``: corner residual RMS, undistorted px; ``ambiguous``: the planar ambiguity flag;
    ``covariance``: (6, 6) over (tx, ty, tz, rx, ry, rz) in the marker frame, metres and radians."""

    T_camera_marker: np.ndarray
    rms_px: float
    ambiguous: bool
    covariance: np.ndarray


class Refusal(StrEnum):
    """Why ``MarkerAnchor.add`` did not keep a pair."""

    INVALID = "invalid"
    """A value not finite, or a position covariance that is not symmetric positive semi-definite."""
    AMBIGUOUS = "ambiguous"
    HIGH_RMS = "high_rms"
    UNCERTAIN = "uncertain"
    """The marker's predicted position error is over ``max_relative_std`` of its distance (far or grazing)."""


class AnchorStatus(StrEnum):
    """Whether the kept pairs give an anchor, and if not, why."""

    ANCHORED = "anchored"
    TOO_FEW_FRAMES = "too_few_frames"
    SHORT_BASELINE = "short_baseline"
    COLLINEAR = "collinear"
    """``centres`` only: the camera centres lie too close to one line for the rotation."""
    INCONSISTENT = "inconsistent"
    """Enough pairs, but fewer than ``min_frames`` of them agree with the fit."""


@dataclass(frozen=True)
class Anchor:
    """The fitted similarity map -> marker.

    ``T_marker_map``: (4, 4) ``[[s R, t], [0, 1]]``: a map point (map units) -> marker frame (m);
    ``scale``: ``s``, metres per map unit; ``frames``: inlier pairs used; ``outliers``: kept pairs left
    out as inconsistent; ``residual_m``: RMS position residual of the inliers (metres; for ``rays`` the
    marker's centre, for ``centres`` the camera's); ``rotation_residual_deg``: RMS angle between each
    inlier's marker orientation and the fitted one; ``baseline_m``, ``breadth_m``: as the settings
    define them, over the inliers.
    """

    T_marker_map: np.ndarray
    scale: float
    frames: int
    outliers: int
    residual_m: float
    rotation_residual_deg: float
    baseline_m: float
    breadth_m: float

    @property
    def similarity(self) -> Similarity:
        """The anchor as ``p_marker = s R p_map + t``."""
        return Similarity(self.T_marker_map[:3, :3] / self.scale, self.T_marker_map[:3, 3], self.scale)

    def to_marker(self, T_map_camera: np.ndarray) -> np.ndarray:
        """(4, 4) or (N, 4, 4) ``T_marker_camera`` (metres) of SLAM poses ``T_map_camera`` of the same shape:
        rotation ``R R_map_camera``, position ``s R c + t``."""
        poses = np.asarray(T_map_camera, dtype=np.float64)
        return apply_similarity(self.similarity, poses.reshape(-1, 4, 4)).reshape(poses.shape)


@dataclass(frozen=True)
class Pair:
    """What a fit needs of one kept pair: ``R_map_marker`` (3, 3); ``offset`` (3,): the marker's position
    seen from the camera, metres, in the map frame's axes; ``c_map`` (3,): the camera centre, map units;
    ``centre`` (3,): the camera centre in the marker frame, metres; ``whiten`` (3, 3): ``W`` with
    ``W^T W`` the inverse covariance of ``offset`` (m^-2)."""

    R_map_marker: np.ndarray
    offset: np.ndarray
    c_map: np.ndarray
    centre: np.ndarray
    whiten: np.ndarray


@dataclass(frozen=True)
class Fit:
    """A fit's rotation ``R_marker_map``, scale, translation and per-pair residuals (metres, radians)."""

    R: np.ndarray
    s: float
    t: np.ndarray
    residual_m: np.ndarray
    angle_rad: np.ndarray


class MarkerAnchor:
    """Pairs of (SLAM pose, marker sighting) of the same frames, and the anchor they give."""

    def __init__(self, settings: AnchorSettings | None = None):
        self.settings = settings or AnchorSettings()
        self._pairs: deque[Pair] = deque(maxlen=self.settings.max_frames)
        self.anchor: Anchor | None = None
        """The latest fit that anchored (None before the first; kept when a later fit does not anchor)."""
        self.status = AnchorStatus.TOO_FEW_FRAMES

    def __len__(self) -> int:
        return len(self._pairs)

    def add(self, T_map_camera: np.ndarray, sighting: MarkerSighting) -> Refusal | None:
        """Keep the pair and refit, or say why not. ``T_map_camera``: (4, 4) SLAM pose of the frame the
        marker was seen in (map units). Arrays of the wrong shape raise ValueError."""
        T_map_camera = check_shape(T_map_camera, "4,4", "T_map_camera", np.float64)
        T_camera_marker = check_shape(sighting.T_camera_marker, "4,4", "T_camera_marker", np.float64)
        covariance = check_shape(sighting.covariance, "6,6", "covariance", np.float64)[:3, :3]
        if not (np.all(np.isfinite(T_map_camera)) and np.all(np.isfinite(T_camera_marker))
                and np.all(np.isfinite(covariance)) and np.isfinite(sighting.rms_px)
                and np.allclose(covariance, covariance.T) and np.linalg.eigvalsh(covariance)[0] >= 0):
            return Refusal.INVALID
        if sighting.ambiguous:
            return Refusal.AMBIGUOUS
        if sighting.rms_px > self.settings.max_rms_px:
            return Refusal.HIGH_RMS
        R_camera_marker, t_camera_marker = T_camera_marker[:3, :3], T_camera_marker[:3, 3]
        if np.sqrt(max(np.trace(covariance), 0.0)) > self.settings.max_relative_std * np.linalg.norm(t_camera_marker):
            return Refusal.UNCERTAIN
        R_map_marker = T_map_camera[:3, :3] @ R_camera_marker
        # the pose covariance is a right perturbation: the marker's origin moves by R_camera_marker rho
        in_map = R_map_marker @ covariance @ R_map_marker.T + self.settings.pose_std_m**2 * np.eye(3)
        self._pairs.append(Pair(R_map_marker, T_map_camera[:3, :3] @ t_camera_marker, T_map_camera[:3, 3],
                                -R_camera_marker.T @ t_camera_marker,
                                np.linalg.cholesky(np.linalg.inv(in_map)).T))
        self.refit()
        return None

    def refit(self) -> Anchor | None:
        """Fit the kept pairs again (``add`` does after every pair); sets and returns ``anchor``, ``status``."""
        s = self.settings
        if len(self) < s.min_frames:
            self.status = AnchorStatus.TOO_FEW_FRAMES
            return None
        pairs = Pair(*(np.array([getattr(pair, name) for pair in self._pairs]) for name in Pair.__dataclass_fields__))
        max_angle = np.radians(s.max_rotation_deg)
        inliers = rotation_inliers(pairs.R_map_marker, max_angle)
        if inliers.sum() < s.min_frames:
            self.status = AnchorStatus.INCONSISTENT
            return None
        fit = self._fit(pairs, inliers)
        closest = inliers & (fit.residual_m <= np.median(fit.residual_m[inliers]))
        if closest.sum() >= s.min_frames:
            inliers, fit = closest, self._fit(pairs, closest)
        baseline, breadth = extents(fit.s * pairs.c_map[inliers])
        if baseline < s.min_baseline_m:
            self.status = AnchorStatus.SHORT_BASELINE
            return None
        if s.method == "centres" and breadth < s.min_breadth_m:
            self.status = AnchorStatus.COLLINEAR
            return None
        for _ in range(3):
            bound = max(s.min_outlier_m, s.outlier_factor * float(np.median(fit.residual_m[inliers])))
            kept = (fit.residual_m <= bound) & (fit.angle_rad <= max_angle)
            if np.array_equal(kept, inliers):
                break
            inliers = kept
            if inliers.sum() < s.min_frames:
                self.status = AnchorStatus.INCONSISTENT
                return None
            fit = self._fit(pairs, inliers)
        baseline, breadth = extents(fit.s * pairs.c_map[inliers])
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = fit.s * fit.R, fit.t
        self.status = AnchorStatus.ANCHORED
        self.anchor = Anchor(T, fit.s, int(inliers.sum()), int((~inliers).sum()), rms(fit.residual_m[inliers]),
                             float(np.degrees(rms(fit.angle_rad[inliers]))), baseline, breadth)
        return self.anchor

    def _fit(self, pairs: Pair, used: np.ndarray) -> Fit:
        """The similarity from the ``used`` rows of ``pairs`` (stacked), with every pair's residuals against it."""
        if self.settings.method == "rays":
            R = Rotation.from_matrix(pairs.R_map_marker[used]).mean().as_matrix().T
            origin, s = marker_origin(pairs.offset[used], pairs.c_map[used], pairs.whiten[used])
            t = -R @ origin
            residual = np.linalg.norm(origin - s * pairs.c_map - pairs.offset, axis=1)
        else:
            R, t, s = umeyama_alignment(pairs.c_map[used], pairs.centre[used], with_scale=True)
            residual = np.linalg.norm(pairs.centre - (s * pairs.c_map @ R.T + t), axis=1)
        return Fit(R, s, t, residual, angles_to(pairs.R_map_marker, R.T))


def marker_origin(offsets: np.ndarray, c_map: np.ndarray, whiten: np.ndarray) -> tuple[np.ndarray, float]:
    """Weighted least-squares ``(u (3,), s)`` of ``u - s c_map_i = offsets_i``: ``offsets`` (N, 3) the marker's
    metric position seen from each camera, in the map frame's axes (m), each equation whitened by its
    (N, 3, 3) ``whiten``; ``c_map`` (N, 3) the camera centres (map units). ``s``: metres per map unit;
    ``u = s o``: the marker's origin ``o`` in the map, scaled to metres."""
    A = np.zeros((len(offsets), 3, 4))
    A[:, :, :3] = np.eye(3)
    A[:, :, 3] = -c_map
    solution = np.linalg.lstsq((whiten @ A).reshape(-1, 4), np.einsum("nij,nj->ni", whiten, offsets).reshape(-1),
                               rcond=None)[0]
    return solution[:3], float(solution[3])


def angles_to(R: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """(N,) angles (radians) between (N, 3, 3) rotations and one (3, 3) ``reference``."""
    return Rotation.from_matrix(np.einsum("ji,njk->nik", reference, R)).magnitude()


def rotation_inliers(R: np.ndarray, max_angle: float) -> np.ndarray:
    """(N,) bool: the (N, 3, 3) rotations within ``max_angle`` (radians) of their robust mean: the chordal
    mean of all, then of the closest half to it, then of those within ``max_angle``."""
    mean = Rotation.from_matrix(R).mean().as_matrix()
    angles = angles_to(R, mean)
    closest = angles <= np.median(angles)
    mean = Rotation.from_matrix(R[closest]).mean().as_matrix()
    return angles_to(R, mean) <= max_angle


def extents(centres: np.ndarray) -> tuple[float, float]:
    """``(baseline, breadth)`` of (N, 3) camera centres: twice their RMS distance from their mean, and from
    their best line."""
    spread = np.linalg.svd(centres - centres.mean(axis=0), compute_uv=False) / np.sqrt(len(centres))
    return 2 * float(np.linalg.norm(spread)), 2 * float(np.linalg.norm(spread[1:]))


def rms(values: np.ndarray) -> float:
    """Root mean square of (N,) values, or of the lengths of (N, 3) vectors."""
    values = np.asarray(values, dtype=np.float64)
    squares = np.sum(values**2, axis=1) if values.ndim == 2 else values**2
    return float(np.sqrt(np.mean(squares)))
