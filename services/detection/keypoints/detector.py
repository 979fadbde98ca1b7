"""Keypoints and their descriptors in one grey image, by one of five methods.

Pixels are those of the input image: x right, y down, the centre of the top-left pixel at (0, 0).

Methods (``KeypointParams.method``):

* ``orb``: OpenCV's ORB (FAST corners ranked by the Harris score over a pyramid of ``levels``
  levels, each ``scale_factor`` smaller; intensity-centroid orientation; rotated BRIEF, 256 bits).
* ``sift``: OpenCV's SIFT (difference of Gaussians; 128 floats), its doubled first octave upsampled
  with ``enable_precise_upscale`` (pixel x to 2x): OpenCV's default upsampling places every keypoint
  about a quarter of a pixel right of and below the feature, at every octave, which a homography
  between two images of different scale turns into a shift of the target (docs/accuracy.md).
* ``akaze``: OpenCV's AKAZE (nonlinear scale space; binary MLDB, 486 bits), from
  ``cv2.xfeatures2d`` in OpenCV 5.
* ``harris`` and ``shi_tomasi``: corners of the response maps of ``services.detection.keypoints.harris``
  on every level of ORB's pyramid, with ORB's sizes and orientations
  (``services.detection.keypoints.corners``), described by ORB's extractor.

Descriptors (``KeypointParams.descriptor``): ``native`` is the method's own (ORB's for the two
corner methods); ``teblid`` computes TEBLID (``cv2.xfeatures2d.TEBLID``, 256 bits) at the same
keypoints, its sampling window scaled for the detector as OpenCV's documentation advises
(``TEBLID_SCALE``).

Spreading (``KeypointParams.spread``): the detector is asked for ``candidates`` times
``max_count`` keypoints, then ``grid`` bucketing or ``anms`` (``services.detection.keypoints.spread``)
keeps at most ``max_count``; ``none`` keeps the ``max_count`` strongest. Descriptors are
computed only for the keypoints kept. ORB's extractor drops keypoints closer than ``EDGE_PX``
to the border, so corners it describes are only taken that far inside.

ORB's placement (``orb_image_points``): OpenCV's ORB finds FAST corners at integer pixels
``x_l`` of level ``l``, an image of ``round(W / s^l)`` x ``round(H / s^l)`` pixels resized with
pixel-centre alignment, but reports them at ``x_l * s^l``. The point that level pixel
shows in the input image is ``(x_l + 0.5) * W / W_l - 0.5`` (per axis), the mapping of every
other pyramid in the project; the difference is about ``-0.5 (s^l - 1)`` px (towards the
top-left) plus a scale error of up to ``(W / W_l - s^l) x_l`` from the rounded level size
(measured in docs/feature-tracking.md). The detector moves ORB's keypoints to the correct point
after describing them (the descriptor is sampled on the level, where ORB's own position is right).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, fields, replace
from typing import Literal

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from services.detection.keypoints.corners import PATCH_PX, corner_keypoints, find_corners, pyramid
from services.detection.keypoints.spread import spread_anms, spread_grid
from services.geometry.shapes import check_shape

__all__ = ["EDGE_PX", "METHODS", "TEBLID_SCALE", "KeypointDetector", "KeypointParams", "Keypoints", "detect_keypoints",
           "orb_image_points", "teblid_available"]

Method = Literal["orb", "sift", "akaze", "harris", "shi_tomasi"]
METHODS: tuple[Method, ...] = ("orb", "sift", "akaze", "harris", "shi_tomasi")
Descriptor = Literal["native", "teblid"]
Spread = Literal["grid", "anms", "none"]
Norm = Literal["hamming", "l2"]

EDGE_PX = 31
"""ORB's border: keypoints closer than this to the image's edge get no ORB descriptor."""
TEBLID_SCALE: dict[str, float] = {"orb": 1.0, "harris": 1.0, "shi_tomasi": 1.0, "sift": 6.75, "akaze": 5.0}
"""TEBLID's sampling-window scale for each detector's keypoint sizes (OpenCV's documentation of TEBLID)."""
_NORMS: dict[int, Norm] = {cv2.NORM_HAMMING: "hamming", cv2.NORM_L2: "l2"}


@dataclass(frozen=True)
class Keypoints:
    """Keypoints found in one image, row ``i`` of every array describing keypoint ``i``, strongest first.

    ``points``: (N, 2) float32 px; ``sizes``: (N,) float32, the diameter of the described
    neighbourhood in px; ``angles``: (N,) float32 degrees in [0, 360), OpenCV's convention
    (clockwise in the image, from x towards y); ``responses``: (N,) float32, the detector's
    strength (comparable within one method only); ``octaves``: (N,) int32, the pyramid level or
    octave it was found at (SIFT: -1 for its upsampled first octave); ``descriptors``: (N, D),
    uint8 for binary descriptors (bits packed, compare with ``norm`` ``hamming``) or float32
    (``l2``). ``method`` names the detector, ``descriptor_type`` the extractor (``ORB``,
    ``TEBLID``, ``SIFT``, ``AKAZE``).
    """

    points: np.ndarray
    sizes: np.ndarray
    angles: np.ndarray
    responses: np.ndarray
    octaves: np.ndarray
    descriptors: np.ndarray
    method: str
    descriptor_type: str
    norm: Norm

    def __post_init__(self) -> None:
        n = len(check_shape(self.points, "N,2", "points"))
        for field in fields(self)[1:5]:
            check_shape(getattr(self, field.name), f"{n}", field.name)
        check_shape(self.descriptors, f"{n},D", "descriptors")

    def __len__(self) -> int:
        return len(self.points)

    @property
    def cv_norm(self) -> int:
        """OpenCV's norm for these descriptors (``cv2.NORM_HAMMING`` or ``cv2.NORM_L2``), for ``cv2.BFMatcher``."""
        return cv2.NORM_HAMMING if self.norm == "hamming" else cv2.NORM_L2


class KeypointParams(BaseModel):
    """Which detector, which descriptor, how many keypoints and how they are spread (see the module docstring).

    The detector is asked for ``candidates`` keypoints per kept one when spreading; ``levels`` and
    ``scale_factor`` make the pyramid of ``orb``, ``harris`` and ``shi_tomasi``; each threshold is one
    method's (named in its description).
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    method: Method = Field(default="orb", description="orb, sift, akaze, harris or shi_tomasi")
    descriptor: Descriptor = Field(default="native", description="native (the method's own; ORB for corners) "
                                                                  "or teblid")
    max_count: int = Field(default=1000, ge=1, le=100000, description="most keypoints kept a frame")
    spread: Spread = Field(default="grid", description="grid (bucketing), anms or none")
    cell_px: int = Field(default=64, ge=8, description="grid: cell side, px")
    candidates: float = Field(default=3.0, ge=1, description="keypoints the detector is asked for per kept one "
                                                              "when spreading")
    anms_robustness: float = Field(default=0.9, gt=0, le=1, description="anms: a keypoint's suppression radius reaches "
                                                                        "the nearest one stronger than its "
                                                                        "response over this")
    levels: int = Field(default=8, ge=1, le=32, description="orb, harris, shi_tomasi: pyramid levels")
    scale_factor: float = Field(default=1.2, gt=1, le=4, description="orb, harris, shi_tomasi: scale between levels")
    fast_threshold: int = Field(default=20, ge=1, le=255, description="orb: FAST threshold, grey levels")
    contrast_threshold: float = Field(default=0.04, gt=0, description="sift: least contrast of a keypoint")
    akaze_threshold: float = Field(default=0.001, gt=0, description="akaze: least detector response")
    corner_quality: float = Field(default=0.01, ge=0, lt=1,
                                  description="harris, shi_tomasi: least response, fraction of the level's largest")
    harris_k: float = Field(default=0.04, gt=0, description="harris: k of the response det - k trace^2")
    block_size: int = Field(default=3, ge=2, description="harris, shi_tomasi: window of the corners' structure "
                                                         "tensor, px")

    @property
    def descriptor_type(self) -> str:
        """The extractor's name: ``TEBLID``, else the method's own (``ORB`` for the corner methods)."""
        if self.descriptor == "teblid":
            return "TEBLID"
        return "ORB" if self.method in ("harris", "shi_tomasi") else self.method.upper()

    @property
    def asked(self) -> int:
        """How many keypoints the detector is asked for before spreading."""
        return self.max_count if self.spread == "none" else int(np.ceil(self.max_count * self.candidates))


def teblid_available() -> bool:
    """Whether this OpenCV build has TEBLID (``cv2.xfeatures2d``, in the contrib modules)."""
    return hasattr(getattr(cv2, "xfeatures2d", None), "TEBLID")


def _feature2d(params: KeypointParams) -> cv2.Feature2D:
    """OpenCV's detector (and native extractor) of ``params.method``; ORB's for the corner methods."""
    p = params
    if p.method == "sift":
        return cv2.SIFT.create(nfeatures=p.asked, contrastThreshold=p.contrast_threshold, enable_precise_upscale=True)
    if p.method == "akaze":
        if not hasattr(getattr(cv2, "xfeatures2d", None), "AKAZE"):
            raise ValueError("AKAZE needs OpenCV's contrib modules (cv2.xfeatures2d.AKAZE), absent from this build")
        return cv2.xfeatures2d.AKAZE.create(threshold=p.akaze_threshold)
    return cv2.ORB.create(nfeatures=p.asked, scaleFactor=p.scale_factor, nlevels=p.levels, edgeThreshold=EDGE_PX,
                          patchSize=PATCH_PX, fastThreshold=p.fast_threshold)


def _teblid(method: str) -> cv2.Feature2D:
    if not teblid_available():
        raise ValueError("TEBLID needs OpenCV's contrib modules (cv2.xfeatures2d.TEBLID), absent from this build")
    return cv2.xfeatures2d.TEBLID.create(TEBLID_SCALE[method])


class KeypointDetector:
    """Finds ``params``' keypoints and descriptors in grey images; builds OpenCV's detectors once.

    ValueError at construction for settings this OpenCV build cannot honour (TEBLID or AKAZE
    without the contrib modules).
    """

    def __init__(self, params: KeypointParams | None = None):
        params = params or KeypointParams()
        self.params = params
        self._corners = params.method in ("harris", "shi_tomasi")
        native = _feature2d(params)
        self._detector = native
        self._extractor = _teblid(params.method) if params.descriptor == "teblid" else native
        self.descriptor_type = params.descriptor_type
        self.norm: Norm = _NORMS[self._extractor.defaultNorm()]
        binary = self._extractor.descriptorType() != cv2.CV_32F
        self._no_descriptors = np.zeros((0, self._extractor.descriptorSize()), np.uint8 if binary else np.float32)

    def detect(self, grey: np.ndarray) -> Keypoints:
        """The keypoints of an (H, W) uint8 image, at most ``params.max_count``, strongest first."""
        if grey.ndim != 2 or grey.dtype != np.uint8:
            raise ValueError(f"image must be (H, W) uint8, not {grey.shape} {grey.dtype}")
        p = self.params
        if self._corners:
            levels = pyramid(grey, p.levels, p.scale_factor)
            corners = find_corners(levels, "harris" if p.method == "harris" else "shi_tomasi", p.asked, p.scale_factor,
                                   p.corner_quality, p.block_size, p.harris_k,
                                   margin=EDGE_PX if p.descriptor == "native" else 0)
            kept = corners.select(self._keep(corners.points, corners.responses, grey.shape))
            keypoints = corner_keypoints(levels, kept, p.scale_factor)
        else:
            found = self._detector.detect(grey, None)
            keypoints = [found[i] for i in self._keep(_points(found), _responses(found), grey.shape)]
        described, descriptors = self._extractor.compute(grey, keypoints) if keypoints else ((), None)
        table = self._table(list(described), descriptors)
        if p.method != "orb":
            return table
        return replace(table, points=orb_image_points(table.points, table.octaves, grey.shape, p.scale_factor))

    def empty(self) -> Keypoints:
        """No keypoints, with descriptors of this detector's width and dtype."""
        return self._table([], None)

    def _keep(self, points: np.ndarray, responses: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
        """Indices of the candidates kept: the ``asked`` strongest, spread, at most ``max_count``."""
        p = self.params
        strongest = np.argsort(-responses, kind="stable")[:p.asked]
        if p.spread == "grid":
            chosen = spread_grid(points[strongest], responses[strongest], (shape[0], shape[1]), p.max_count, p.cell_px)
        elif p.spread == "anms":
            chosen = spread_anms(points[strongest], responses[strongest], p.max_count, p.anms_robustness)
        else:
            chosen = np.arange(min(p.max_count, len(strongest)))
        return strongest[chosen]

    def _table(self, keypoints: list[cv2.KeyPoint], descriptors: np.ndarray | None) -> Keypoints:
        """The described keypoints as arrays, strongest first (ORB's extractor returns them by level).

        Each field is read off the keypoints in the order they come and the arrays are ordered after:
        reading a ``cv2.KeyPoint``'s field is what costs here, so no reordered list is built to read again.
        """
        responses = _responses(keypoints)
        order = np.argsort(-responses, kind="stable")
        octaves = np.array([k.octave for k in keypoints], np.int32)[order]
        if self.params.method == "sift":  # the octave is the low byte, signed
            octaves = (octaves & 0xFF).astype(np.int8).astype(np.int32)
        kept = self._no_descriptors if descriptors is None else descriptors[order]
        sizes = np.array([k.size for k in keypoints], np.float32)[order]
        angles = np.array([k.angle for k in keypoints], np.float32)[order]
        return Keypoints(points=_points(keypoints)[order], sizes=sizes, angles=angles, responses=responses[order],
                         octaves=octaves, descriptors=kept.astype(self._no_descriptors.dtype, copy=False),
                         method=self.params.method, descriptor_type=self.descriptor_type, norm=self.norm)


def orb_image_points(points: np.ndarray, octaves: np.ndarray, shape: tuple[int, ...],
                     scale_factor: float) -> np.ndarray:
    """(N, 2) float32 input-image pixels of (N, 2) keypoint ``points`` as OpenCV's ORB reports them
    (``x_l * s^l`` for pixel ``x_l`` of level ``octaves`` (N,) ``l``) in an image of ``shape`` (H, W)
    with ORB's ``scale_factor`` ``s``: ``(x_l + 0.5) * W / W_l - 0.5`` per axis, with ORB's level size
    ``W_l = round(W / s^l)`` computed as ORB computes it (in float32)."""
    scales = np.power(np.float64(scale_factor), octaves.astype(np.float64)).astype(np.float32)[:, None]
    size = np.array([shape[1], shape[0]], np.float32)
    level_size = np.floor(size * (np.float32(1.0) / scales) + np.float32(0.5))
    level_points = points.astype(np.float64) / scales
    return ((level_points + 0.5) * (size / level_size) - 0.5).astype(np.float32)


def _points(keypoints: Sequence[cv2.KeyPoint]) -> np.ndarray:
    if not keypoints:
        return np.zeros((0, 2), np.float32)
    return np.asarray(cv2.KeyPoint.convert(keypoints), np.float32).reshape(-1, 2)


def _responses(keypoints: Sequence[cv2.KeyPoint]) -> np.ndarray:
    return np.array([k.response for k in keypoints], np.float32)


def detect_keypoints(grey: np.ndarray, params: KeypointParams | None = None) -> Keypoints:
    """The keypoints of an (H, W) uint8 image (builds a ``KeypointDetector``; keep one to detect in many images)."""
    return KeypointDetector(params).detect(grey)
