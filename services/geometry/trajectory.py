"""Smooth periodic trajectories: sums of sines, look-at camera paths and rigid-body paths.

Every path is a pure function of time (seconds), so a frame can be evaluated in any order.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.geometry.camera import look_at
from services.geometry.rotation import matrix_from_rotvec
from services.geometry.se3 import make_transform


@dataclass(frozen=True)
class SinePath:
    """``p(t) = centre + sum_k amplitudes[k] * sin(2 pi frequencies_hz[k] t + phases[k])``, per axis.

    ``centre`` is (D,); ``amplitudes``, ``frequencies_hz`` and ``phases`` (radians) are (K, D).
    """

    centre: np.ndarray
    amplitudes: np.ndarray
    frequencies_hz: np.ndarray
    phases: np.ndarray

    @classmethod
    def random(cls, rng: np.random.Generator, centre, amplitude, period_range_s: tuple[float, float],
               terms: int = 2) -> SinePath:
        """``terms`` sines per axis with random periods in ``period_range_s`` and random phases.

        The per-axis amplitude is split among the terms, so ``|p(t) - centre| <= amplitude`` axis by axis.
        """
        centre = np.asarray(centre, dtype=np.float64)
        amplitude = np.broadcast_to(np.asarray(amplitude, dtype=np.float64), centre.shape)
        weights = rng.uniform(0.5, 1.0, (terms, centre.size))
        weights /= weights.sum(axis=0)
        periods = rng.uniform(*period_range_s, (terms, centre.size))
        return cls(centre, weights * amplitude, 1.0 / periods, rng.uniform(0, 2 * np.pi, (terms, centre.size)))

    def __call__(self, t: float) -> np.ndarray:
        """(D,) position at time ``t`` seconds."""
        return self.centre + (self.amplitudes * np.sin(2 * np.pi * self.frequencies_hz * t + self.phases)).sum(axis=0)


@dataclass(frozen=True)
class LookAtPath:
    """A camera at ``eye(t)`` looking at ``target(t)``, rolled by ``roll(t)`` (radians, about its z axis).

    ``up`` (3,) is the world direction the image's top points to at zero roll.
    """

    eye: SinePath
    target: SinePath
    roll: SinePath
    up: np.ndarray

    def pose(self, t: float) -> np.ndarray:
        """(4, 4) ``T_world_camera`` at time ``t`` seconds."""
        roll = self.roll(t)[0]
        c, s = np.cos(roll), np.sin(roll)
        rolled = make_transform(np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]), np.zeros(3))
        return look_at(self.eye(t), self.target(t), self.up) @ rolled


@dataclass(frozen=True)
class RigidPath:
    """A rigid body at ``position(t)`` with orientation ``exp(rotvec(t)) @ R_base`` (all in the world frame)."""

    position: SinePath
    rotvec: SinePath
    R_base: np.ndarray

    def pose(self, t: float) -> np.ndarray:
        """(4, 4) ``T_world_body`` at time ``t`` seconds."""
        return make_transform(matrix_from_rotvec(self.rotvec(t)) @ self.R_base, self.position(t))
