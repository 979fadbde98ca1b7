"""Bright blobs in infrared images (retro-reflective spheres, LEDs), and the result every blob detector returns.

Pixels are those of the input image: x right, y down, the centre of the top-left pixel at (0, 0).

``detect_ir_blobs`` thresholds the image and finds its 8-connected components by border
following (``cv2.findContours``, external borders only, so a component's holes count as
inside it). Per component, in a small window around it (measured in compiled code, ``measure_kernel``):

* centroid: intensity-weighted, ``sum(w * p) / sum(w)`` with ``w = max(I - background, 0)``
  over the component grown by one pixel (the anti-aliased rim just below the threshold
  belongs to the blob; pixels above the threshold of another component do not);
* area: its pixels; radius: ``sqrt(area / pi)``;
* perimeter and circularity: of the border polygon through the outer pixels' centres,
  ``4 pi area_polygon / perimeter**2`` as ``cv2.SimpleBlobDetector`` measures it;
* roundness: ``sqrt(l_min / l_max)`` of the weighted second moments' eigenvalues, 1 for a disc;
  solidity: polygon area over its convex hull's area;
* flags (``BlobFlag``): a blob that is not round (roundness below ``min_roundness``) or not
  convex (solidity below ``min_solidity``) is MERGED when its weight, summed across its major
  axis in 1 px slices, has a waist (a slice lighter than the heaviest slice on each side by
  ``waist_depth`` of it: two blobs run together), else OCCLUDED (partly hidden or cut).
  CLIPPED: it touches the image border, so part of it may be outside;
* quality: roundness times solidity, in (0, 1].

A blob flagged MERGED or OCCLUDED is also split (``split.split_two_discs``: two discs fitted to its
weights); where the fit holds, two rows flagged SPLIT follow the blob's own: the two discs' centres,
areas and radii (circularity and perimeter those of the disc, quality one less the fit's residual RMS
as a fraction of its peak), CLIPPED too when the blob is.

Flagged blobs are reported, not dropped: a consumer that wants clean centroids keeps
``blobs.clean()``. Filters drop components outside ``[min_area, max_area]`` pixels, outside
``[min_radius, max_radius]`` px or below ``min_circularity`` (noise, streaks).
"""

from __future__ import annotations

import enum
import math
from collections.abc import Sequence
from dataclasses import dataclass, fields

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from services.detection.blobs import measure_kernel, merged_kernel
from services.geometry.shapes import check_shape

__all__ = ["BlobFlag", "Blobs", "IrBlobParams", "ShapeParams", "detect_ir_blobs", "moment_shape", "shape_flags"]

WINDOW_PAD = 2
"""Pixels around a component's bounding box in the window its centroid and shape are measured in."""
BACKGROUND_STRIDE = 8
"""The estimated background is the median of every ``BACKGROUND_STRIDE``-th pixel along both axes."""


class BlobFlag(enum.IntFlag):
    """Why a blob's centroid may not be the centre of one round spot (bits of ``Blobs.flags``)."""

    MERGED = measure_kernel.MERGED
    """Two or more blobs run together: the centroid lies between them."""
    OCCLUDED = measure_kernel.OCCLUDED
    """Not round and no waist: partly hidden or cut, the centroid is off the spot's centre."""
    CLIPPED = measure_kernel.CLIPPED
    """Touches the image border: part of the blob may lie outside the image."""
    SPLIT = measure_kernel.SPLIT
    """One of two discs fitted to the MERGED or OCCLUDED blob in the row before the pair (``split``)."""


@dataclass(frozen=True)
class Blobs:
    """Blobs found in one image, row ``i`` of every array describing blob ``i``.

    ``centroids``: (N, 2) float64 px (x right, y down); ``area``: (N,) float64 px^2;
    ``radius``: (N,) float64 px; ``perimeter``: (N,) float64 px; ``circularity``: (N,) float64
    in [0, 1], ``4 pi area / perimeter**2`` (NaN where the method does not measure it);
    ``quality``: (N,) float64 in [0, 1], higher is better (each method says how it is made);
    ``flags``: (N,) uint8, bits of ``BlobFlag``.
    """

    centroids: np.ndarray
    area: np.ndarray
    radius: np.ndarray
    perimeter: np.ndarray
    circularity: np.ndarray
    quality: np.ndarray
    flags: np.ndarray

    def __post_init__(self) -> None:
        n = len(check_shape(self.centroids, "N,2", "centroids"))
        for field in fields(self)[1:]:
            check_shape(getattr(self, field.name), f"{n}", field.name)

    def __len__(self) -> int:
        return len(self.centroids)

    @classmethod
    def from_rows(cls, rows: Sequence[tuple[float, ...]] | np.ndarray) -> Blobs:
        """Blobs from ``(x, y, area, radius, perimeter, circularity, quality, flags)`` rows (or an (N, 8) array of
        them)."""
        table = np.asarray(rows, np.float64).reshape(-1, 8)
        return cls(table[:, :2].copy(), table[:, 2].copy(), table[:, 3].copy(), table[:, 4].copy(),
                   table[:, 5].copy(), table[:, 6].copy(), table[:, 7].astype(np.uint8))

    def select(self, keep: np.ndarray) -> Blobs:
        """The blobs ``keep`` picks: an (N,) bool mask or an index array."""
        return Blobs(**{field.name: getattr(self, field.name)[keep] for field in fields(self)})

    def flagged(self, flag: BlobFlag) -> np.ndarray:
        """(N,) bool: the blobs with ``flag`` set."""
        return (self.flags & int(flag)) != 0

    def clean(self) -> Blobs:
        """The blobs with no flag set (the parts of split blobs are left out with their blobs)."""
        return self.select(self.flags == 0)


class ShapeParams(BaseModel):
    """Filters and flags every method that measures its blobs' pixels shares (IR and colour blobs)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    min_area: float = Field(default=3.0, ge=0, description="smallest blob kept, px^2")
    max_area: float = Field(default=10000.0, gt=0, description="largest blob kept, px^2")
    min_circularity: float = Field(default=0.3, ge=0, le=1, description="least circularity of a blob kept, "
                                                                        "4 pi area / perimeter^2")
    min_roundness: float = Field(default=0.8, ge=0, le=1, description="below this roundness a blob is flagged "
                                                                      "(merged or occluded)")
    waist_depth: float = Field(default=0.05, ge=0, le=1, description="a flagged blob whose weight dips this much "
                                                                     "between two heavier parts is merged")

    @model_validator(mode="after")
    def _an_area_range(self) -> ShapeParams:
        if self.min_area > self.max_area:
            raise ValueError(f"area range [{self.min_area}, {self.max_area}] is empty")
        return self


class IrBlobParams(BaseModel):
    """Settings of ``detect_ir_blobs`` (see the module docstring), beside ``ShapeParams``'s."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    threshold: float = Field(default=60.0, ge=0, description="grey level blobs exceed")
    background: float | None = Field(default=None, ge=0, description="grey level subtracted from the centroid "
                                                                      "weights; default: estimated per image (the "
                                                                      "median of a pixel grid)")
    min_radius: float = Field(default=0.0, ge=0, description="smallest blob radius kept, px")
    max_radius: float = Field(default=math.inf, ge=0, description="largest blob radius kept, px")
    min_solidity: float = Field(default=0.85, ge=0, le=1, description="below this solidity (area over its convex "
                                                                      "hull's) a blob is flagged")

    @model_validator(mode="after")
    def _a_radius_range(self) -> IrBlobParams:
        if self.min_radius > self.max_radius:
            raise ValueError(f"radius range [{self.min_radius}, {self.max_radius}] is empty")
        return self


def check_mono(image: np.ndarray) -> np.ndarray:
    """``image`` as an (H, W) uint8 or uint16 array; ValueError naming what it got otherwise."""
    image = np.asarray(image)
    if image.ndim != 2 or image.dtype not in (np.uint8, np.uint16):
        raise ValueError(f"IR blob detection needs a mono8 or mono16 (H, W) image, not {image.dtype} {image.shape}")
    return image


def detect_ir_blobs(image: np.ndarray, params: IrBlobParams | None = None, shape: ShapeParams | None = None) -> Blobs:
    """Bright blobs of ``image`` ((H, W) uint8 or uint16 grey levels, the scale of ``params.threshold``), in the
    order found.

    Every component is measured in its window (bounding box grown by ``WINDOW_PAD``) by one call of the
    compiled ``measure_kernel.measure``, then filtered, shaped, flagged and split by one of ``blob_rows``; neither
    holds Python's lock."""
    image = np.ascontiguousarray(check_mono(image))  # the kernel is compiled for C-ordered images only
    params = params or IrBlobParams()
    shape = shape or ShapeParams()
    height, width = image.shape
    if image.dtype == np.uint8:
        binary = cv2.threshold(image, params.threshold, 255, cv2.THRESH_BINARY)[1]
    else:
        binary = cv2.compare(image, params.threshold, cv2.CMP_GT)  # type: ignore[call-overload]
    contours, _ = cv2.findContours(binary, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    if not contours:
        return Blobs.from_rows([])
    starts = np.zeros(len(contours) + 1, np.int64)
    np.cumsum([len(c) for c in contours], out=starts[1:])
    background = grid_median(image) if params.background is None else params.background
    table, weights = measure_kernel.measure(image, binary, np.concatenate(contours).reshape(-1, 2), starts,
                                            float(background), WINDOW_PAD)
    return Blobs.from_rows(measure_kernel.blob_rows(
        table, weights, width, height, shape.min_area, shape.max_area, params.min_radius, params.max_radius,
        shape.min_circularity, shape.min_roundness, params.min_solidity, shape.waist_depth))


def grid_median(image: np.ndarray) -> float:
    """The median grey level of every ``BACKGROUND_STRIDE``-th pixel of ``image`` along both axes (the mean of
    the two middle values of an even count, as ``np.median``)."""
    sample = image[::BACKGROUND_STRIDE, ::BACKGROUND_STRIDE].ravel()
    middle = len(sample) // 2
    if len(sample) % 2:
        return float(np.partition(sample, middle)[middle])
    low, high = np.partition(sample, [middle - 1, middle])[middle - 1:middle + 1].tolist()
    return (low + high) / 2.0


def moment_shape(moments: dict[str, float]) -> tuple[tuple[float, float], tuple[float, float], float]:
    """From ``cv2.moments`` of a weight window: the centroid ``(x, y)`` px in the window, the major
    axis ``(cos, sin)`` (a unit vector) and the roundness ``sqrt(l_min / l_max)`` of the covariance
    (``measure_kernel.moment_shape``)."""
    x, y, cos, sin, roundness = measure_kernel.moment_shape(moments["m00"], moments["m10"], moments["m01"],
                                                            moments["mu20"], moments["mu11"], moments["mu02"])
    return (x, y), (cos, sin), roundness


def shape_flags(weights: np.ndarray, centroid: tuple[float, float], axis: tuple[float, float], irregular: bool,
                waist_depth: float) -> BlobFlag:
    """MERGED, OCCLUDED or no flag for one blob (see the module docstring).

    ``weights``: (h, w) float window, 0 outside the blob; ``centroid``: ``(x, y)`` px in the window;
    ``axis``: unit major axis ``(cos, sin)``; ``irregular``: the blob failed the roundness or solidity test.
    """
    if not irregular:
        return BlobFlag(0)
    return BlobFlag.MERGED if has_waist(weights, centroid, axis, waist_depth) else BlobFlag.OCCLUDED


def has_waist(weights: np.ndarray, centroid: tuple[float, float], axis: tuple[float, float], depth: float) -> bool:
    """Whether the weight summed across ``axis`` in 1 px slices (each pixel shared linearly between
    the two nearest slices) dips, somewhere inside, below ``1 - depth`` of the heaviest slice on each side
    (compiled: ``merged_kernel.has_waist``)."""
    return bool(merged_kernel.has_waist(merged_kernel.as_weights(weights), centroid[0], centroid[1], axis[0], axis[1],
                                        depth))
