"""Blobs of any image by the scale-normalised Laplacian of Gaussian, over a range of scales.

The image (grey levels scaled to [0, 1]) is blurred with a Gaussian of each scale ``s`` of a
geometric series from ``min_sigma`` to ``max_sigma`` px (``cv2.GaussianBlur``) and its
Laplacian taken (``cv2.Laplacian``, the 3x3 five-point stencil). The response is
``-s**2 * Laplacian``: positive on bright blobs, negative on dark ones, and independent of
scale for a blob seen at its own scale. A detection is a maximum of the squared response
over its 26 neighbours in space and scale, above ``threshold**2``, where the blurred image
curves alike in every direction: a point whose Hessian's eigenvalues differ in sign or by
more than ``edge_ratio`` times lies on an edge or a ridge and is dropped. Its position and
scale are refined by a parabola through the response and its two neighbours along x, y and
log-scale; its characteristic radius is ``sqrt(2) * s`` (a disc of radius r answers most
strongly at ``s = r / sqrt(2)``).

Non-maximum suppression across scales: from the strongest down, a detection whose disc
covers more than ``overlap`` of the smaller disc's area with an already kept one is dropped.
Both signs take part, so the ring of opposite sign around a strong blob is not reported;
then only the detections of the sign the polarity asks for are kept.

Result (``Blobs``): area ``pi r**2``, perimeter ``2 pi r``, circularity not measured (NaN);
quality = ``|response| / (2 / e)``, capped at 1: the contrast of a disc with the same
response (``2 / e`` is the response of a white disc on black at its scale); CLIPPED when
the disc crosses the image border.
"""

from __future__ import annotations

import math
from typing import Literal

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from services.detection.blobs.bright import BlobFlag, Blobs

__all__ = ["LogBlobParams", "detect_log_blobs", "log_stack"]

DISC_RESPONSE = 2.0 / math.e
"""The scale-normalised LoG response at the centre of a white disc on black, at its own scale."""
_NEIGHBOURS = np.ones((3, 3), np.uint8)


class LogBlobParams(BaseModel):
    """Settings of ``detect_log_blobs`` (see the module docstring)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    min_sigma: float = Field(default=1.0, ge=0.3, description="smallest scale, px")
    max_sigma: float = Field(default=10.0, ge=0.3, description="largest scale, px")
    scales: int = Field(default=12, ge=3, description="scales from min_sigma to max_sigma, in geometric steps")
    threshold: float = Field(default=0.05, gt=0, le=1, description="least response (contrast, 0 to 1)")
    polarity: Literal["bright", "dark", "both"] = Field(default="bright", description="bright blobs, dark blobs "
                                                                                      "or both")
    overlap: float = Field(default=0.5, ge=0, le=1, description="a blob whose disc covers more than this share of "
                                                                "a stronger one's (the smaller disc's area) is "
                                                                "dropped")
    edge_ratio: float = Field(default=10.0, gt=1, description="the largest ratio of principal curvatures a blob "
                                                              "may have (more: an edge or a ridge)")

    @model_validator(mode="after")
    def _a_scale_range(self) -> LogBlobParams:
        if self.min_sigma > self.max_sigma:
            raise ValueError(f"need min_sigma <= max_sigma, not {self.min_sigma} and {self.max_sigma}")
        return self

    def sigmas(self) -> np.ndarray:
        """(S,) float64 scales, px."""
        return np.geomspace(self.min_sigma, self.max_sigma, self.scales)


def as_unit_grey(image: np.ndarray) -> np.ndarray:
    """(H, W) float32 grey levels in [0, 1] of a mono8/mono16 (H, W) or bgr8 (H, W, 3) image."""
    image = np.asarray(image)
    if image.ndim == 3 and image.shape[2] == 3 and image.dtype == np.uint8:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if image.ndim != 2 or image.dtype not in (np.uint8, np.uint16):
        raise ValueError(f"LoG blob detection needs a mono8, mono16 or bgr8 image, not {image.dtype} {image.shape}")
    return image.astype(np.float32) / np.float32(np.iinfo(image.dtype).max)


def log_stack(grey: np.ndarray, sigmas: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For each scale ``s`` of ``sigmas`` ((S,) px): ``Gaussian_s * grey`` and the scale-normalised
    response ``-s**2 * Laplacian(Gaussian_s * grey)``, two (S, H, W) float32 stacks, of ``grey``
    ((H, W) float32)."""
    blurred = np.empty((len(sigmas), *grey.shape), np.float32)
    stack = np.empty_like(blurred)
    for k, sigma in enumerate(sigmas):
        blurred[k] = cv2.GaussianBlur(grey, (0, 0), float(sigma), borderType=cv2.BORDER_REPLICATE)
        stack[k] = cv2.Laplacian(blurred[k], cv2.CV_32F, ksize=1, borderType=cv2.BORDER_REPLICATE)
        stack[k] *= -float(sigma) ** 2
    return blurred, stack


def on_edge(layer: np.ndarray, r: int, c: int, edge_ratio: float) -> bool:
    """Whether the point (row ``r``, column ``c``) of ``layer`` ((H, W)) is a ridge or an edge rather
    than a blob: its Hessian's eigenvalues differ in sign or by more than ``edge_ratio`` times,
    that is ``trace**2 / det >= (edge_ratio + 1)**2 / edge_ratio`` or ``det <= 0``."""
    if not (0 < r < layer.shape[0] - 1 and 0 < c < layer.shape[1] - 1):
        return False
    window = layer[r - 1:r + 2, c - 1:c + 2].astype(np.float64)
    dxx = window[1, 2] - 2.0 * window[1, 1] + window[1, 0]
    dyy = window[2, 1] - 2.0 * window[1, 1] + window[0, 1]
    dxy = (window[2, 2] - window[2, 0] - window[0, 2] + window[0, 0]) / 4.0
    det = dxx * dyy - dxy * dxy
    return bool(det <= 0.0 or (dxx + dyy) ** 2 * edge_ratio >= det * (edge_ratio + 1.0) ** 2)


def detect_log_blobs(image: np.ndarray, params: LogBlobParams | None = None) -> Blobs:
    """Blobs of ``image`` (mono8/mono16 (H, W) or bgr8 (H, W, 3)), strongest first."""
    params = params or LogBlobParams()
    sigmas = params.sigmas()
    blurred, stack = log_stack(as_unit_grey(image), sigmas)
    energy = stack * stack
    spatial = np.stack([cv2.dilate(layer, _NEIGHBOURS) for layer in energy])
    neighbourhood = spatial.copy()
    neighbourhood[1:] = np.maximum(neighbourhood[1:], spatial[:-1])
    neighbourhood[:-1] = np.maximum(neighbourhood[:-1], spatial[1:])
    scale_index, rows, cols = np.nonzero((energy == neighbourhood) & (energy > params.threshold**2))
    candidates = [refine_peak(stack, sigmas, int(k), int(r), int(c))
                  for k, r, c in zip(scale_index, rows, cols, strict=True)
                  if not on_edge(blurred[k], int(r), int(c), params.edge_ratio)]
    candidates.sort(key=lambda found: -abs(found[3]))
    sign = {"bright": 1.0, "dark": -1.0, "both": 0.0}[params.polarity]
    kept = [found for found in suppress_overlaps(candidates, params.overlap) if sign * found[3] >= 0.0]
    height, width = stack.shape[1:]
    out = []
    for x, y, radius, response in kept:
        clipped = x - radius < -0.5 or y - radius < -0.5 or x + radius > width - 0.5 or y + radius > height - 0.5
        out.append((x, y, math.pi * radius**2, radius, 2.0 * math.pi * radius, math.nan,
                    min(abs(response) / DISC_RESPONSE, 1.0), int(BlobFlag.CLIPPED) if clipped else 0))
    return Blobs.from_rows(out)


def parabola_offset(before: float, at: float, after: float) -> tuple[float, float]:
    """Vertex of the parabola through (-1, before), (0, at), (1, after): offset in [-0.5, 0.5] and value."""
    curvature = before - 2.0 * at + after
    if curvature == 0.0:
        return 0.0, at
    offset = float(np.clip(0.5 * (before - after) / curvature, -0.5, 0.5))
    return offset, at + 0.25 * (after - before) * offset


def refine_peak(stack: np.ndarray, sigmas: np.ndarray, k: int, r: int, c: int) -> tuple[float, float, float, float]:
    """``(x, y, radius, response)`` of the peak at scale ``k``, row ``r``, column ``c`` of ``stack``,
    refined along each axis where both neighbours exist."""
    scales, height, width = stack.shape
    at = float(stack[k, r, c])
    dx = parabola_offset(float(stack[k, r, c - 1]), at, float(stack[k, r, c + 1]))[0] if 0 < c < width - 1 else 0.0
    dy = parabola_offset(float(stack[k, r - 1, c]), at, float(stack[k, r + 1, c]))[0] if 0 < r < height - 1 else 0.0
    log_sigma, response = math.log(sigmas[k]), at
    if 0 < k < scales - 1:
        step, (ds, response) = math.log(sigmas[1] / sigmas[0]), parabola_offset(float(stack[k - 1, r, c]), at,
                                                                                float(stack[k + 1, r, c]))
        log_sigma += ds * step
    return c + dx, r + dy, math.sqrt(2.0) * math.exp(log_sigma), response


def suppress_overlaps(candidates: list[tuple[float, float, float, float]],
                      overlap: float) -> list[tuple[float, float, float, float]]:
    """Of ``(x, y, radius, response)`` candidates, strongest first, those not covering more than
    ``overlap`` of the smaller disc's area with a stronger one kept before."""
    kept: list[tuple[float, float, float, float]] = []
    for candidate in candidates:
        x, y, radius, _ = candidate
        if all(disc_overlap(math.hypot(x - kx, y - ky), radius, kr) <= overlap for kx, ky, kr, _ in kept):
            kept.append(candidate)
    return kept


def disc_overlap(distance: float, r1: float, r2: float) -> float:
    """Area two discs of radii ``r1``, ``r2`` with centres ``distance`` apart share, over the smaller's area."""
    small, large = min(r1, r2), max(r1, r2)
    if distance >= small + large:
        return 0.0
    if distance <= large - small:
        return 1.0
    a = small**2 * math.acos((distance**2 + small**2 - large**2) / (2.0 * distance * small))
    b = large**2 * math.acos((distance**2 + large**2 - small**2) / (2.0 * distance * large))
    c = 0.5 * math.sqrt((-distance + small + large) * (distance + small - large)
                        * (distance - small + large) * (distance + small + large))
    return (a + b - c) / (math.pi * small**2)
