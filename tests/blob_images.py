"""Test images of blobs with exact ground truth: anti-aliased discs, each pixel lit by the share
of it a disc covers (supersampled), brightest disc winning where discs overlap."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

SUPERSAMPLE = 8


def disc_coverage(discs: Sequence[tuple[float, float, float]], shape: tuple[int, int]) -> np.ndarray:
    """(H, W) float64 in [0, 1]: per pixel, the largest share of it one disc ``(x, y, radius)`` px covers
    (pixel centres at integer coordinates, x right, y down)."""
    height, width = shape
    coverage = np.zeros(shape)
    offsets = (np.arange(SUPERSAMPLE) + 0.5) / SUPERSAMPLE - 0.5
    for x, y, radius in discs:
        x0, y0 = max(int(x - radius) - 1, 0), max(int(y - radius) - 1, 0)
        x1, y1 = min(int(x + radius) + 2, width), min(int(y + radius) + 2, height)
        if x0 >= x1 or y0 >= y1:
            continue
        xs = (np.arange(x0, x1)[:, None] + offsets).ravel()
        ys = (np.arange(y0, y1)[:, None] + offsets).ravel()
        inside = ((xs[None, :] - x) ** 2 + (ys[:, None] - y) ** 2 <= radius**2).astype(np.float64)
        share = inside.reshape(y1 - y0, SUPERSAMPLE, x1 - x0, SUPERSAMPLE).mean(axis=(1, 3))
        np.maximum(coverage[y0:y1, x0:x1], share, out=coverage[y0:y1, x0:x1])
    return coverage


def disc_image(discs: Sequence[tuple[float, float, float]], shape: tuple[int, int] = (120, 160),
               background: int = 12, peak: int = 240) -> np.ndarray:
    """(H, W) uint8 image: ``background`` grey with the discs ``(x, y, radius)`` px at ``peak``."""
    return (background + (peak - background) * disc_coverage(discs, shape) + 0.5).astype(np.uint8)
