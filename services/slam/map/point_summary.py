"""A map point's summary, computed from its observations: representative descriptor, mean viewing
direction and the range of distances at which ORB's pyramid can find it again.

The representative descriptor is the observation's descriptor with the least median Hamming distance
to the others; the viewing direction is the mean of the unit rays from the observing cameras' centres
to the point (world frame); the distance range comes from the first observation: its distance times
the scale of its pyramid level is the largest, that divided by the scale of the coarsest level the least.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.slam.map.keyframe import Keyframe

__all__ = ["PointDraft", "PointSummaries", "median_descriptors", "summarise"]


@dataclass(frozen=True)
class PointDraft:
    """A point's summary to compute: ``position`` (3,) world, ``observations`` (keyframe, keypoint
    index) in observation order, ``first`` (keyframe, keypoint index) that sets the distance range."""

    position: np.ndarray
    observations: list[tuple[Keyframe, int]]
    first: tuple[Keyframe, int]


@dataclass(frozen=True)
class PointSummaries:
    """P points' ``descriptors`` (P, 32) uint8, ``normals`` (P, 3), ``min_distances``, ``max_distances`` (P,)."""

    descriptors: np.ndarray
    normals: np.ndarray
    min_distances: np.ndarray
    max_distances: np.ndarray


def median_descriptors(descriptors: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """(P, 32): each point's descriptor with the least median Hamming distance to its others (the
    first when it has one or two); ``descriptors`` (O, 32) the points' observations one after the
    other, ``counts`` (P,) how many each."""
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
    chosen = starts.copy()
    for count in np.unique(counts[counts > 2]).tolist():
        rows = np.flatnonzero(counts == count)
        group = descriptors[starts[rows, None] + np.arange(count)]
        distances = np.bitwise_count(group[:, :, None, :] ^ group[:, None, :, :]).sum(axis=3, dtype=np.int32)
        medians = np.sort(distances, axis=2)[:, :, (count - 1) // 2]
        chosen[rows] = starts[rows] + np.argmin(medians, axis=1)
    return descriptors[chosen].copy()


def _gather(keyframes: list[Keyframe], indices: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(descriptors (O, 32), levels (O,), centres (O, 3))`` of keypoint ``indices[o]`` of ``keyframes[o]``."""
    ids = np.array([k.id for k in keyframes], np.int64)
    descriptors, levels = np.zeros((len(ids), 32), np.uint8), np.zeros(len(ids), np.int64)
    centres = np.zeros((len(ids), 3))
    for keyframe in {k.id: k for k in keyframes}.values():
        rows = np.flatnonzero(ids == keyframe.id)
        descriptors[rows] = keyframe.features.descriptors[indices[rows]]
        levels[rows] = keyframe.features.levels[indices[rows]]
        centres[rows] = keyframe.centre
    return descriptors, levels, centres


def summarise(drafts: list[PointDraft], scale_factor: float, levels: int) -> PointSummaries:
    """The summaries of ``drafts`` for a pyramid of ``levels`` levels, each ``scale_factor`` smaller
    than the one before (needs no lock: keyframes' features never change, and a pose change replaces
    a keyframe's ``centre`` rather than writing into it)."""
    counts = np.array([len(d.observations) for d in drafts], np.int64)
    observed = [k for d in drafts for k, _ in d.observations]
    descriptors, _, centres = _gather(observed, np.array([i for d in drafts for _, i in d.observations], np.int64))
    positions = np.array([d.position for d in drafts], np.float64).reshape(-1, 3)
    rays = np.repeat(positions, counts, axis=0) - centres
    rays /= np.maximum(np.linalg.norm(rays, axis=1), 1e-12)[:, None]
    owner = np.repeat(np.arange(len(drafts)), counts)
    mean = np.stack([np.bincount(owner, rays[:, c], len(drafts)) for c in range(3)], axis=1)
    normals = mean / np.maximum(np.linalg.norm(mean, axis=1), 1e-12)[:, None]
    _, first_levels, first_centres = _gather([d.first[0] for d in drafts],
                                             np.array([d.first[1] for d in drafts], np.int64))
    max_distances = np.linalg.norm(positions - first_centres, axis=1) * scale_factor ** first_levels
    return PointSummaries(median_descriptors(descriptors, counts), normals,
                          max_distances / scale_factor ** (levels - 1), max_distances)
