"""Coloured markers found by their hue: a colour model learnt from a sample rectangle, a per-pixel
in/out mask, and the blobs of that mask.

Colours are HSV as ``cv2.cvtColor(..., cv2.COLOR_BGR2HSV_FULL)`` gives them for bgr8 images:
hue, saturation and value each 0..255, the hue circle in 256 steps. Hue is circular: its
mean is the direction of the mean unit vector ``(cos h, sin h)`` over the sample and its
spread the circular standard deviation ``sqrt(-2 ln R)``, ``R`` that vector's length.

A pixel is in when its hue is within ``width`` spreads of the mean (at least
``min_half_width_deg``) the short way round the circle, and its saturation and value are at
least the model's minimum: ``SAMPLE_SHARE`` of the sample's mean, never below
``SATURATION_FLOOR`` / ``VALUE_FLOOR`` (under which hue means little), so shading and noise
within the marker keep its pixels in.

Blobs are the mask's 8-connected components (``cv2.connectedComponentsWithStats``): area in
pixels, centroid the mean of its pixel centres, perimeter from its border pixels: the pixel
sides a blob pixel shares with a pixel outside it, counted, times ``pi / 4`` (over all
directions, a curve is on average ``pi / 4`` of its length along the pixel axes), so a disc of
radius r measures about ``2 pi r``. Circularity ``4 pi area / perimeter**2`` (capped at 1),
radius ``sqrt(area / pi)``. Roundness and flags as ``services.detection.blobs.bright`` makes them for
IR blobs, with every pixel of a blob weighted 1 and solidity not tested; quality = roundness.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from services.detection.blobs.bright import BlobFlag, Blobs, ShapeParams, moment_shape, shape_flags

__all__ = ["ColourBlobParams", "HueModel", "HueWindow", "colour_mask", "crack_perimeters", "detect_colour_blobs",
           "to_hsv"]

SATURATION_FLOOR = 40.0
VALUE_FLOOR = 40.0
SAMPLE_SHARE = 0.5
HUE_STEPS = 256
"""Hue codes per turn of the colour circle (``COLOR_BGR2HSV_FULL``)."""
CRACK_TO_LENGTH = math.pi / 4.0


def to_hsv(image: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 HSV (hue 0..255 for a full turn) of a bgr8 (H, W, 3) image."""
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise ValueError(f"colour blob detection needs a bgr8 (H, W, 3) image, not {image.dtype} {image.shape}")
    return cv2.cvtColor(image, cv2.COLOR_BGR2HSV_FULL)


def circular_mean_spread(angles: np.ndarray) -> tuple[float, float]:
    """Circular mean in [0, 2 pi) and circular standard deviation of ``angles`` ((N,) radians)."""
    c, s = float(np.mean(np.cos(angles))), float(np.mean(np.sin(angles)))
    length = min(math.hypot(c, s), 1.0)
    spread = math.sqrt(-2.0 * math.log(length)) if length > 0 else math.inf
    return math.atan2(s, c) % (2.0 * math.pi), spread


@dataclass(frozen=True)
class HueModel:
    """A marker colour: ``hue_deg`` circular mean in [0, 360), ``spread_deg`` circular standard
    deviation, ``min_saturation`` and ``min_value`` (0..255) a pixel must reach."""

    hue_deg: float
    spread_deg: float
    min_saturation: float
    min_value: float

    @classmethod
    def from_sample(cls, image: np.ndarray, rect: tuple[int, int, int, int]) -> HueModel:
        """The colour of the pixels of ``image`` (bgr8 (H, W, 3)) inside ``rect`` = ``(x, y, w, h)`` px."""
        hsv = to_hsv(image)
        x, y, w, h = (int(v) for v in rect)
        if w <= 0 or h <= 0 or x < 0 or y < 0 or x + w > hsv.shape[1] or y + h > hsv.shape[0]:
            raise ValueError(f"sample rectangle {rect} (x, y, w, h) is empty or not inside the "
                             f"{hsv.shape[1]}x{hsv.shape[0]} image")
        sample = hsv[y:y + h, x:x + w].reshape(-1, 3).astype(np.float64)
        mean, spread = circular_mean_spread(sample[:, 0] * (2.0 * math.pi / HUE_STEPS))
        floors = np.maximum(SAMPLE_SHARE * sample[:, 1:].mean(axis=0), (SATURATION_FLOOR, VALUE_FLOOR))
        return cls(math.degrees(mean), math.degrees(spread), float(floors[0]), float(floors[1]))


class ColourBlobParams(BaseModel):
    """Settings of ``colour_mask`` and ``detect_colour_blobs``, beside ``ShapeParams``'s: the hue window."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    width: float = Field(default=3.0, gt=0, description="half-width of the hue window, in spreads of the colour")
    min_half_width_deg: float = Field(default=5.0, ge=0, description="least half-width of the hue window, deg")


class HueWindow(BaseModel):
    """A marker colour given by hand rather than learnt from a sample (``HueModel.from_sample``)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    hue_deg: float = Field(default=0.0, ge=0, lt=360, description="the markers' hue, degrees")
    hue_width_deg: float = Field(default=8.0, gt=0, le=180, description="half-width of the hue window, deg")
    min_saturation: float = Field(default=80.0, ge=0, le=255, description="least saturation, 0..255")
    min_value: float = Field(default=60.0, ge=0, le=255, description="least value, 0..255")

    def model(self, params: ColourBlobParams) -> HueModel:
        """The ``HueModel`` whose window under ``params`` is ``hue_deg`` +- ``hue_width_deg``."""
        return HueModel(self.hue_deg, self.hue_width_deg / params.width, self.min_saturation, self.min_value)


def hue_table(model: HueModel, params: ColourBlobParams) -> np.ndarray:
    """(256,) bool: which hue codes are in the model's window."""
    half_width = max(params.width * model.spread_deg, params.min_half_width_deg)
    degrees = np.arange(HUE_STEPS) * (360.0 / HUE_STEPS)
    return np.abs((degrees - model.hue_deg + 180.0) % 360.0 - 180.0) <= half_width


def colour_mask(image: np.ndarray, model: HueModel, params: ColourBlobParams | None = None) -> np.ndarray:
    """(H, W) bool: the pixels of ``image`` (bgr8 (H, W, 3)) of the model's colour."""
    params = params or ColourBlobParams()
    hsv = to_hsv(image)
    return (hue_table(model, params)[hsv[..., 0]] & (hsv[..., 1] >= model.min_saturation)
            & (hsv[..., 2] >= model.min_value))


def crack_perimeters(labels: np.ndarray, count: int) -> np.ndarray:
    """(count,) float64: per label of ``labels`` ((H, W) int), the pixel sides its pixels share with
    pixels of another label or the outside of the image, times ``pi / 4``; label 0's entry is 0."""
    padded = np.pad(labels, 1)
    sides = np.zeros(count, np.int64)
    for a, b in ((padded[:, 1:], padded[:, :-1]), (padded[1:, :], padded[:-1, :])):
        differ = a != b
        sides += np.bincount(a[differ], minlength=count)[:count] + np.bincount(b[differ], minlength=count)[:count]
    sides[0] = 0
    return sides * CRACK_TO_LENGTH


def detect_colour_blobs(image: np.ndarray, model: HueModel, params: ColourBlobParams | None = None,
                        shape: ShapeParams | None = None) -> Blobs:
    """Blobs of the model's colour in ``image`` (bgr8 (H, W, 3)), largest first."""
    params = params or ColourBlobParams()
    shape = shape or ShapeParams()
    mask = colour_mask(image, model, params).view(np.uint8)
    count, labels, stats, centres = cv2.connectedComponentsWithStats(mask, connectivity=8)
    perimeters = crack_perimeters(labels, count)
    height, width = mask.shape
    rows = []
    for label in np.argsort(-stats[1:, cv2.CC_STAT_AREA], kind="stable") + 1:
        x, y, w, h, area = (int(v) for v in stats[label])
        circularity = min(4.0 * math.pi * area / perimeters[label] ** 2, 1.0)
        if not (shape.min_area <= area <= shape.max_area and circularity >= shape.min_circularity):
            continue
        weights = (labels[y:y + h, x:x + w] == label).astype(np.float32)
        centroid, axis, roundness = moment_shape(cv2.moments(weights))
        flags = shape_flags(weights, centroid, axis, roundness < shape.min_roundness, shape.waist_depth)
        if x == 0 or y == 0 or x + w == width or y + h == height:
            flags |= BlobFlag.CLIPPED
        rows.append((*centres[label], area, math.sqrt(area / math.pi), perimeters[label], circularity,
                     roundness, int(flags)))
    return Blobs.from_rows(rows)
