"""How trackable an image is as a target: how many keypoints, how spread out, how repeated.

Measured on the keypoints a target of the image would get (``targets.target_features``):

* ``keypoints``: their count over the pyramid. Too few and a partly hidden, small or blurred view
  leaves too few matches.
* ``coverage``: the fraction of the cells of a ``GRID`` x ``GRID`` grid over the image holding at
  least one keypoint, and ``entropy``: the entropy of the keypoints' distribution over the cells
  divided by its maximum ``log(GRID^2)`` (1: spread evenly; 0: all in one cell). A target whose
  texture sits in one corner is lost as soon as that corner leaves the view, and a pose from
  clustered points is poorly constrained.
* ``repeated``: the fraction of keypoints with a twin elsewhere in the image. Matching a frame keypoint
  to the target passes Lowe's ratio test only when its nearest target descriptor is clearly nearer
  than the second; a keypoint whose descriptor has another of the same pyramid level, away from its
  own position, within ``REPEAT_FRACTION`` of the typical distance between unrelated descriptors is
  matched about as well by the twin, so its matches fail the test (or land on the wrong copy).
  Tiles, grids, text in one font and other periodic patterns score high.

The verdict is ``poor`` (do not print it), ``fair`` (works, with the warnings' limits) or ``good``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np

from services.detection.keypoints.detector import KeypointParams
from services.estimation.targets.features import DEFAULT_FEATURE, Extractor, feature_params, is_binary, to_grey
from services.estimation.targets.target import target_features

__all__ = [
    "GRID",
    "MIN_COVERAGE",
    "MIN_ENTROPY",
    "MIN_KEYPOINTS",
    "REPEAT_FRACTION",
    "Trackability",
    "check_image",
    "repeated_fraction",
]

GRID = 8
MIN_KEYPOINTS = 100
"""Fewer keypoints over the whole pyramid make the image ``poor``."""
GOOD_KEYPOINTS = 500
"""Fewer keypoints than this (but at least ``MIN_KEYPOINTS``) draw a warning."""
MIN_COVERAGE = 0.6
MIN_ENTROPY = 0.85
REPEAT_FRACTION = 0.3
"""A twin lies within this fraction of the median distance between unrelated descriptors of its level:
below what rich unique texture gives, far above what copies of a tile give (docs/feature-targets.md)."""
MAX_REPEATED = 0.2
"""More repeated keypoints than this draw a warning; more than ``POOR_REPEATED`` make the image ``poor``."""
POOR_REPEATED = 0.5
TWIN_RADIUS_PX = 8.0
"""Keypoints closer than this (level pixels) are one feature seen twice (e.g. at two of ORB's octaves)."""
NEIGHBOURS = 8
TYPICAL_SAMPLE = 256
"""Descriptors of a level whose pairwise distances give the typical distance between unrelated ones."""

Verdict = Literal["good", "fair", "poor"]


@dataclass(frozen=True)
class Trackability:
    """``keypoints``: count; ``coverage``: fraction of grid cells with a keypoint; ``entropy``: normalised
    entropy of the keypoints over the cells, [0, 1]; ``repeated``: fraction of keypoints with a twin;
    ``verdict``: ``good``, ``fair`` or ``poor``; ``warnings``: one line each, empty when good."""

    keypoints: int
    coverage: float
    entropy: float
    repeated: float
    verdict: Verdict
    warnings: tuple[str, ...]


def check_image(image: np.ndarray, feature: str | KeypointParams = DEFAULT_FEATURE, extract: Extractor | None = None,
                max_levels: int | None = None) -> Trackability:
    """How trackable ``image`` ((H, W) or (H, W, 3) BGR, uint8 or uint16) is with the keypoints of
    ``extract`` (default ``make_extractor(feature)``, a feature's name or detector settings) over its pyramid
    (at most ``max_levels`` levels, default the target's own: ``targets.target_levels``)."""
    grey = to_grey(image)
    detector = feature_params(feature) if isinstance(feature, str) else feature
    keypoints, descriptors, levels = target_features(grey, detector, extract, max_levels)
    count = len(keypoints)
    coverage, entropy = spread(keypoints, (grey.shape[1], grey.shape[0]))
    repeated = repeated_fraction(keypoints, descriptors, levels)
    warnings, poor = [], False
    if count < GOOD_KEYPOINTS:
        poor = count < MIN_KEYPOINTS
        warnings.append(f"only {count} keypoints (want {GOOD_KEYPOINTS}): too little texture to be found "
                        "small, blurred or partly hidden")
    if coverage < MIN_COVERAGE:
        warnings.append(f"keypoints cover {coverage:.0%} of the image (want {MIN_COVERAGE:.0%}): the target is "
                        "lost when its textured part leaves the view")
    if entropy < MIN_ENTROPY:
        warnings.append(f"keypoints are clustered (spread {entropy:.2f}, want {MIN_ENTROPY}): the pose rests on "
                        "a small part of the image")
    if repeated > MAX_REPEATED:
        poor = poor or repeated > POOR_REPEATED
        warnings.append(f"{repeated:.0%} of keypoints repeat elsewhere in the image (want at most "
                        f"{MAX_REPEATED:.0%}): repeated texture makes matches ambiguous")
    verdict: Verdict = "poor" if poor else "fair" if warnings else "good"
    return Trackability(count, coverage, entropy, repeated, verdict, tuple(warnings))


def spread(keypoints: np.ndarray, size_px: tuple[int, int]) -> tuple[float, float]:
    """``(coverage, entropy)`` of (N, 2) pixels over a ``GRID`` x ``GRID`` grid of a ``size_px`` = (W, H) image
    (module docstring); (0, 0) without keypoints."""
    if len(keypoints) == 0:
        return 0.0, 0.0
    cells = np.clip(((keypoints + 0.5) / np.array(size_px) * GRID).astype(np.int64), 0, GRID - 1)
    counts = np.bincount(cells[:, 1] * GRID + cells[:, 0], minlength=GRID * GRID)
    p = counts[counts > 0] / len(keypoints)
    return float(np.count_nonzero(counts) / counts.size), float(0.0 - np.sum(p * np.log(p)) / math.log(GRID * GRID))


def repeated_fraction(keypoints: np.ndarray, descriptors: np.ndarray, levels: np.ndarray) -> float:
    """Fraction of (N,) keypoints (level-0 pixels (N, 2), descriptors (N, D), pyramid ``levels`` (N,))
    with a twin: another keypoint of its level, at least ``TWIN_RADIUS_PX`` level pixels away, whose
    descriptor lies within ``REPEAT_FRACTION`` of the level's median pairwise descriptor distance."""
    if len(keypoints) == 0:
        return 0.0
    norm = cv2.NORM_HAMMING if is_binary(descriptors) else cv2.NORM_L2
    matcher = cv2.BFMatcher(norm)
    twins = 0
    for level in np.unique(levels):
        rows = np.flatnonzero(levels == level)
        if len(rows) < 3:
            continue
        own, positions = descriptors[rows], keypoints[rows]
        typical = typical_distance(own[:TYPICAL_SAMPLE])
        radius = TWIN_RADIUS_PX * 2.0 ** int(level)
        for neighbours in matcher.knnMatch(own, own, k=min(NEIGHBOURS, len(rows))):
            for m in neighbours:
                if np.hypot(*(positions[m.trainIdx] - positions[m.queryIdx])) > radius:
                    twins += m.distance < REPEAT_FRACTION * typical
                    break
    return twins / len(keypoints)


def typical_distance(descriptors: np.ndarray) -> float:
    """Median distance between distinct rows of (S, D) descriptors, S >= 2: Hamming for binary, L2 for float."""
    first, second = np.triu_indices(len(descriptors), 1)
    if is_binary(descriptors):
        distances = np.unpackbits(descriptors[first] ^ descriptors[second], axis=1).sum(axis=1)
    else:
        distances = np.linalg.norm(descriptors[first].astype(np.float64) - descriptors[second], axis=1)
    return float(np.median(distances))
