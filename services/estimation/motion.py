"""A constant-velocity motion model of one rigid body, for predicting its pose at the next instant.

The model keeps the body's last two fitted poses ``T_world_body`` (4, 4) with their stamps (int
nanoseconds) and, when known, their covariances ((6, 6), ``RigidFit``'s convention: world-frame
``(dtheta, dt)``, radians then metres). From them it holds two velocities, both in the world frame:

* angular: ``omega`` (3,) rad/s, the rotation vector per second with ``R_1 = exp(omega dt) R_0``;
* linear: ``v`` (3,) m/s, of the body origin, ``t_1 = t_0 + v dt``;

and predicts at a stamp ``s``, ``tau = s - s_1`` seconds after the newer pose::

    R(s) = exp(omega tau) R_1,    t(s) = t_1 + v tau

(the rotation turns about the body origin, the origin moves on a line; between the two poses this is
the spherical linear interpolation of the rotation and the linear one of the translation).

The predicted covariance (same convention) carries the two fits' covariances through the
extrapolation, ``(1 + r)^2 S_1 + r^2 S_0`` with ``r = tau / dt`` (the fits taken as independent), plus
what an unmodelled acceleration adds: ``(tau^2 / 2)^2`` times the squared ``angular_acceleration``
(rad/s^2) on each rotation axis and the squared ``acceleration`` (m/s^2) on each translation axis.

A pose newer than ``max_gap_s`` after the previous one starts the model afresh (the old velocity
says nothing any more), and no prediction is made more than ``max_gap_s`` after the newest pose.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from services.geometry.rotation import matrix_from_rotvec, rotvec_from_matrix
from services.geometry.se3 import check_transform, make_transform
from services.geometry.shapes import check_shape

__all__ = ["DEFAULT_MOTION", "MotionOptions", "Prediction", "ConstantVelocity"]

NS_PER_S = 1_000_000_000


class MotionOptions(BaseModel):
    """How long a motion holds, and the accelerations it ignores (see the module docstring)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    max_gap_s: float = Field(default=0.2, gt=0, allow_inf_nan=False,
                             description="longest time between two poses of one motion, and from the newest pose "
                                         "to a prediction, s: a motion older than that is forgotten")
    acceleration: float = Field(default=5.0, ge=0, allow_inf_nan=False,
                                description="spread (one sigma, per axis) of the linear accelerations the model "
                                            "ignores, which grows a prediction's covariance, m/s^2")
    angular_acceleration: float = Field(default=20.0, ge=0, allow_inf_nan=False,
                                        description="spread (one sigma, per axis) of the angular accelerations the "
                                                    "model ignores, rad/s^2")

    @property
    def max_gap_ns(self) -> int:
        """``max_gap_s`` in nanoseconds (at least 1)."""
        return max(1, round(self.max_gap_s * NS_PER_S))


DEFAULT_MOTION = MotionOptions()


@dataclass(frozen=True)
class Prediction:
    """A predicted ``T_world_body`` (4, 4) at ``stamp_ns`` and its (6, 6) covariance (world-frame
    ``(dtheta, dt)``, as ``RigidFit``'s)."""

    stamp_ns: int
    T_world_body: np.ndarray
    covariance: np.ndarray


@dataclass(frozen=True)
class _Sample:
    stamp_ns: int
    T_world_body: np.ndarray
    covariance: np.ndarray


class ConstantVelocity:
    """One body's constant-velocity model: ``update`` with each fitted pose, in stamp order; ``predict``."""

    def __init__(self, options: MotionOptions = DEFAULT_MOTION):
        self.options = options
        self._samples: list[_Sample] = []
        self._velocity: tuple[np.ndarray, np.ndarray] | None = None
        self._acceleration = np.diag(np.repeat([options.angular_acceleration**2, options.acceleration**2], 3))
        """(6, 6) the squared unmodelled accelerations, rad/s^2 then m/s^2, on the diagonal."""

    def reset(self) -> None:
        """Forget every pose."""
        self._samples = []
        self._velocity = None

    @property
    def ready(self) -> bool:
        """Whether two poses are known, so velocities (and predictions) exist."""
        return len(self._samples) == 2

    def update(self, stamp_ns: int, T_world_body: np.ndarray, covariance: np.ndarray | None = None) -> None:
        """Take a fitted pose ``T_world_body`` (4, 4) at ``stamp_ns`` with its (6, 6) covariance (or None: zero).

        A stamp not after the newest one is refused (ValueError); one more than ``max_gap_s`` after it
        starts the model afresh.
        """
        T = check_transform(T_world_body, "T_world_body")
        sigma = np.zeros((6, 6)) if covariance is None else check_shape(covariance, "6,6", "covariance", np.float64)
        if self._samples:
            newest = self._samples[-1].stamp_ns
            if stamp_ns <= newest:
                raise ValueError(f"stamp {stamp_ns} ns is not after the newest pose's, {newest} ns")
            if stamp_ns - newest > self.options.max_gap_ns:
                self._samples = []
        self._samples = [*self._samples[-1:], _Sample(int(stamp_ns), T.copy(), sigma)]
        self._velocity = self._velocities() if self.ready else None

    def velocity(self) -> tuple[np.ndarray, np.ndarray]:
        """``(omega, v)``: (3,) world-frame angular velocity (rad/s) and (3,) linear velocity (m/s) of the
        origin; ValueError before two poses are known."""
        if self._velocity is None:
            raise ValueError("a velocity needs two poses")
        return self._velocity

    def _velocities(self) -> tuple[np.ndarray, np.ndarray]:
        """``velocity`` from the two poses known."""
        old, new = self._samples
        dt = (new.stamp_ns - old.stamp_ns) / NS_PER_S
        R_old, R_new = old.T_world_body[:3, :3], new.T_world_body[:3, :3]
        omega = rotvec_from_matrix(R_new @ R_old.T) / dt
        v = (new.T_world_body[:3, 3] - old.T_world_body[:3, 3]) / dt
        return omega, v

    def predict(self, stamp_ns: int) -> Prediction | None:
        """The pose at ``stamp_ns``, None before two poses are known or more than ``max_gap_s`` after the newest."""
        if not self.ready:
            return None
        old, new = self._samples
        if stamp_ns - new.stamp_ns > self.options.max_gap_ns:
            return None
        omega, v = self.velocity()
        tau = (stamp_ns - new.stamp_ns) / NS_PER_S
        R, t = new.T_world_body[:3, :3], new.T_world_body[:3, 3]
        T = make_transform(matrix_from_rotvec(omega * tau) @ R, t + v * tau)
        ratio = (stamp_ns - new.stamp_ns) / (new.stamp_ns - old.stamp_ns)
        drift = (0.5 * tau**2) ** 2 * self._acceleration
        covariance = (1 + ratio) ** 2 * new.covariance + ratio**2 * old.covariance + drift
        return Prediction(int(stamp_ns), T, (covariance + covariance.T) / 2)
