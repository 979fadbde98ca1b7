"""Synthetic bundle-adjustment problems for the SLAM optimisation tests and benchmark.

A cloud of points in a box 5 to 9 m in front of a row of keyframes that look at its middle; each
keyframe observes each point it sees (inside a 640x480 image, in front) with probability
``seen``; pixels get Gaussian noise of ``noise_px`` times the observation's sigma per axis, and a
fraction of the observations are replaced by uniformly random pixels at least ``GROSS_PX`` from the
true one (gross outliers), at most one
per point and only on points seen three times or more: a point seen as often wrong as right has no
robust estimate (under a Huber loss such points drift away without bound). The start
given to the solver is the truth perturbed: free poses by ``start_deg`` and ``start_m``, points by
``start_point_m`` per axis (Gaussian). Frames: OpenCV camera frames, world z forward, y down.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.geometry.camera import intrinsics, look_at
from services.geometry.rotation import matrix_from_rotvec
from services.geometry.se3 import invert, transform_points
from services.slam.optimisation import BundleProblem

WIDTH, HEIGHT = 640, 480
PYRAMID_SCALE = 1.2
"""Sigma of an observation at pyramid level ``l`` is ``PYRAMID_SCALE ** l`` (with ``levels``)."""
GROSS_PX = 20.0


@dataclass(frozen=True)
class SyntheticProblem:
    """``problem`` as the solver gets it; ``poses`` (keyframe id -> (4, 4) T_camera_world) and
    ``points`` ((N, 3) world, row i = point id i) the truth; ``gross``: (M,) bool, the observations
    replaced by random pixels."""

    problem: BundleProblem
    poses: dict[int, np.ndarray]
    points: np.ndarray
    gross: np.ndarray


def keyframe_poses(count: int) -> dict[int, np.ndarray]:
    """``count`` keyframes (ids 0..count-1) on a gentle arc 2 m wide, all looking at (0, 0, 7)."""
    poses = {}
    for k, s in enumerate(np.linspace(-1.0, 1.0, count)):
        eye = np.array([s, 0.2 * np.sin(3 * s), 0.3 * s * s])
        poses[k] = invert(look_at(eye, np.array([0.0, 0.0, 7.0]), np.array([0.0, -1.0, 0.0])))
    return poses


def perturbed_pose(T: np.ndarray, rng: np.random.Generator, angle_deg: float, distance_m: float) -> np.ndarray:
    """``T`` rotated by ``angle_deg`` about a random axis and moved ``distance_m`` in a random direction."""
    axis, direction = rng.normal(size=3), rng.normal(size=3)
    D = np.eye(4)
    D[:3, :3] = matrix_from_rotvec(axis / np.linalg.norm(axis) * np.radians(angle_deg))
    D[:3, 3] = direction / np.linalg.norm(direction) * distance_m
    return D @ T


def gross_observations(rng: np.random.Generator, point_ids: np.ndarray, fraction: float) -> np.ndarray:
    """(M,) bool: about ``fraction`` of the M observations, at most one of each point seen three times or more."""
    ids, first, counts = np.unique(point_ids, return_index=True, return_counts=True)
    order = np.argsort(point_ids, kind="stable")
    starts = np.searchsorted(point_ids[order], ids)
    eligible = counts >= 3
    chance = min(1.0, fraction * len(point_ids) / max(1, int(eligible.sum())))
    picked = eligible & (rng.random(len(ids)) < chance)
    gross = np.zeros(len(point_ids), dtype=bool)
    gross[order[starts[picked] + rng.integers(0, counts[picked])]] = True
    return gross


def random_pixels(rng: np.random.Generator, true: np.ndarray) -> np.ndarray:
    """(N, 2) uniformly random pixels of the image, each at least ``GROSS_PX`` from its row of ``true``."""
    pixels = rng.uniform((0, 0), (WIDTH - 1, HEIGHT - 1), size=true.shape)
    close = np.linalg.norm(pixels - true, axis=1) < GROSS_PX
    while close.any():
        pixels[close] = rng.uniform((0, 0), (WIDTH - 1, HEIGHT - 1), size=(int(close.sum()), 2))
        close = np.linalg.norm(pixels - true, axis=1) < GROSS_PX
    return pixels


def synthetic_problem(rng: np.random.Generator, *, keyframes: int = 10, points: int = 1000, noise_px: float = 1.0,
                      gross_fraction: float = 0.1, fixed: tuple[int, ...] = (0, 1), seen: float = 0.8,
                      levels: int = 0, start_deg: float = 1.0, start_m: float = 0.05,
                      start_point_m: float = 0.05, poses: dict[int, np.ndarray] | None = None) -> SyntheticProblem:
    """A problem as the module docstring describes; ``levels`` > 0 gives each observation a random
    pyramid level below it (sigma ``PYRAMID_SCALE ** level``), 0 leaves ``sigmas`` None (all 1);
    ``poses``: the keyframes' true ``T_camera_world`` (default ``keyframe_poses(keyframes)``)."""
    K = intrinsics(WIDTH, HEIGHT, 64.0)
    truth = keyframe_poses(keyframes) if poses is None else poses
    cloud = rng.uniform((-3.0, -2.0, 5.0), (3.0, 2.0, 9.0), size=(points, 3))
    frame_ids, point_ids, pixels = [], [], []
    for k, T in truth.items():
        camera = transform_points(T, cloud)
        uv = camera[:, :2] / camera[:, 2:] * K[[0, 1], [0, 1]] + K[:2, 2]
        visible = (camera[:, 2] > 0) & np.all((uv >= 0) & (uv <= (WIDTH - 1, HEIGHT - 1)), axis=1)
        visible &= rng.random(points) < seen
        frame_ids.append(np.full(int(visible.sum()), k))
        point_ids.append(np.flatnonzero(visible))
        pixels.append(uv[visible])
    frame_array, point_array = np.concatenate(frame_ids), np.concatenate(point_ids)
    observed = np.concatenate(pixels)
    sigmas = PYRAMID_SCALE ** rng.integers(0, levels, len(observed)) if levels else np.ones(len(observed))
    observed = observed + rng.normal(size=observed.shape) * (noise_px * sigmas)[:, None]
    gross = gross_observations(rng, point_array, gross_fraction)
    observed[gross] = random_pixels(rng, observed[gross])
    start = {k: T if k in fixed else perturbed_pose(T, rng, start_deg, start_m) for k, T in truth.items()}
    start_points = cloud + rng.normal(scale=start_point_m, size=cloud.shape)
    problem = BundleProblem(K=K, poses=start, points={i: p for i, p in enumerate(start_points)},
                            frame_ids=frame_array.astype(np.int64), point_ids=point_array.astype(np.int64),
                            pixels=observed, fixed=frozenset(fixed), sigmas=sigmas if levels else None)
    return SyntheticProblem(problem, truth, cloud, gross)


def pose_problem(seed: int, count: int = 1000, levels: int = 4) -> tuple[np.ndarray, ...]:
    """One keyframe's pose-only problem: ``(K, T, points, pixels, sigmas, gross, start)``, the true
    ``T_camera_world`` (4, 4) of a keyframe of ``keyframe_poses``, (N, 3) world points in its view,
    their pixels (N, 2) with noise of each (N,) sigma (random pyramid levels below ``levels``), 10 %
    replaced by random pixels (``gross`` (N,) bool), and a start 1 deg and 5 cm off."""
    rng = np.random.default_rng(seed)
    T = keyframe_poses(5)[1]
    points = rng.uniform((-3.0, -2.0, 5.0), (3.0, 2.0, 9.0), size=(count, 3))
    K = intrinsics(WIDTH, HEIGHT, 64.0)
    camera = transform_points(T, points)
    pixels = camera[:, :2] / camera[:, 2:] * K[[0, 1], [0, 1]] + K[:2, 2]
    sigmas = PYRAMID_SCALE ** rng.integers(0, levels, count)
    pixels += rng.normal(size=pixels.shape) * sigmas[:, None]
    gross = rng.random(count) < 0.1
    pixels[gross] = random_pixels(rng, pixels[gross])
    return K, T, points, pixels, sigmas, gross, perturbed_pose(T, rng, 1.0, 0.05)
