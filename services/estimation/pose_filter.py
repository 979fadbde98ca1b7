"""A One Euro filter on a stream of poses: a still target stops shaking, a moving one does not lag.

The One Euro filter (Casiez, Roussel and Vogel, CHI 2012) is a first-order low-pass filter whose
cutoff rises with the signal's speed: ``fc = min_cutoff_hz + beta * |speed|``. A still signal is
smoothed hard (``min_cutoff_hz``), a fast one barely (its cutoff far above its motion), so jitter
goes without the lag a fixed low-pass adds. The speed is itself low-passed at ``derivative_cutoff_hz``.
Each step with ``dt`` seconds since the previous sample blends by ``alpha = 1 / (1 + 1 / (2 pi fc dt))``.

On a pose ``T_camera_target`` (4, 4):

* translation, component by component: ``t_hat <- t_hat + alpha (t - t_hat)``, each axis with its own
  speed (m/s) and cutoff (``min_cutoff_hz``, ``beta`` in s/m);
* rotation, as one rotation vector: the step from the filtered rotation to the measured one is
  ``r = log(R_hat^T R)`` (a rotation vector in the filtered target frame); the angular velocity is
  ``r / dt`` (rad/s), low-passed as a vector, and its length sets the cutoff (``rotation_min_cutoff_hz``,
  ``rotation_beta`` in s/rad); then ``R_hat <- R_hat exp(alpha r)``, the spherical linear interpolation
  from ``R_hat`` towards ``R`` by ``alpha``. Working on the step rather than on the rotation's own vector
  keeps the filter free of the vector's wrap at pi and of the choice of origin.

The first pose passes unchanged; so does one more than ``max_gap_s`` after the previous (a target
seen again after a loss starts afresh).
"""

from __future__ import annotations

import math

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from services.geometry.rotation import matrix_from_rotvec, rotvec_from_matrix
from services.geometry.se3 import check_transform, make_transform

__all__ = ["OneEuroOptions", "OneEuroPoseFilter"]

NS_PER_S = 1_000_000_000


class OneEuroOptions(BaseModel):
    """The One Euro filter's cutoffs and speed coefficients.

    The defaults suit the tracker's poses of a target a few tenths of a metre away: a still target's pose
    moves by about 0.01 mm and 0.01 deg a frame, a hand-held one by millimetres and tenths of a degree,
    so the cutoff stays near ``min_cutoff_hz`` for the first and far above the motion for the second
    (docs/feature-targets.md has the figures). A noisier estimator needs smaller betas."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    min_cutoff_hz: float = Field(default=0.5, gt=0, allow_inf_nan=False, description="the translation's cutoff "
                                                                                      "at rest, Hz")
    beta: float = Field(default=10000.0, ge=0, allow_inf_nan=False, description="the translation cutoff's rise "
                                                                                "with speed, s/m")
    rotation_min_cutoff_hz: float = Field(default=0.5, gt=0, allow_inf_nan=False, description="the rotation's "
                                                                                               "cutoff at rest, Hz")
    rotation_beta: float = Field(default=500.0, ge=0, allow_inf_nan=False, description="the rotation cutoff's rise "
                                                                                       "with speed, s/rad")
    derivative_cutoff_hz: float = Field(default=3.0, gt=0, allow_inf_nan=False, description="the cutoff of the "
                                                                                            "speeds, Hz")
    max_gap_s: float = Field(default=0.2, gt=0, allow_inf_nan=False, description="a longer pause between poses "
                                                                                 "restarts the filter, s")


def smoothing(cutoff_hz: float | np.ndarray, dt: float) -> float | np.ndarray:
    """The blend ``alpha`` in (0, 1] of a first-order low-pass at ``cutoff_hz`` over a step of ``dt`` seconds."""
    return 1.0 / (1.0 + 1.0 / (2 * math.pi * cutoff_hz * dt))


class OneEuroPoseFilter:
    """Filters one target's poses in stamp order (see the module's docstring)."""

    def __init__(self, options: OneEuroOptions | None = None):
        self.options = options or OneEuroOptions()
        self.reset()

    def reset(self) -> None:
        """Forget the past: the next pose passes unchanged."""
        self._stamp_ns: int | None = None
        self._R = np.eye(3)
        self._t = np.zeros(3)
        self._velocity = np.zeros(3)
        self._angular = np.zeros(3)

    def __call__(self, stamp_ns: int, T_camera_target: np.ndarray) -> np.ndarray:
        """The filtered (4, 4) pose of ``T_camera_target`` (4, 4) at ``stamp_ns``; ValueError for a stamp not
        after the previous one."""
        T = check_transform(T_camera_target, "T_camera_target")
        o = self.options
        if self._stamp_ns is not None and stamp_ns <= self._stamp_ns:
            raise ValueError(f"stamp {stamp_ns} ns is not after the previous pose's, {self._stamp_ns} ns")
        if self._stamp_ns is None or stamp_ns - self._stamp_ns > round(o.max_gap_s * NS_PER_S):
            self.reset()
            self._stamp_ns, self._R, self._t = int(stamp_ns), T[:3, :3].copy(), T[:3, 3].copy()
            return T.copy()
        dt = (stamp_ns - self._stamp_ns) / NS_PER_S
        self._stamp_ns = int(stamp_ns)
        derivative = smoothing(o.derivative_cutoff_hz, dt)
        self._velocity += derivative * ((T[:3, 3] - self._t) / dt - self._velocity)
        self._t += smoothing(o.min_cutoff_hz + o.beta * np.abs(self._velocity), dt) * (T[:3, 3] - self._t)
        step = rotvec_from_matrix(self._R.T @ T[:3, :3])
        self._angular += derivative * (step / dt - self._angular)
        alpha = smoothing(o.rotation_min_cutoff_hz + o.rotation_beta * float(np.linalg.norm(self._angular)), dt)
        self._R = self._R @ matrix_from_rotvec(alpha * step)
        return make_transform(self._R, self._t)
