"""Camera paths of the scenes: a hand-held camera in front of a plane, looking at it."""

from __future__ import annotations

import numpy as np

from services.geometry.trajectory import LookAtPath, SinePath

PERIOD_RANGE_S = (5.0, 14.0)


def plane_viewing_path(rng: np.random.Generator, near: float, far: float, lateral: tuple[float, float],
                       wander: tuple[float, float], roll: float) -> LookAtPath:
    """A camera between ``near`` and ``far`` metres in front of the plane z = 0 (on its +z side).

    The eye sways by up to ``lateral`` (x, y) metres; it looks at a point of the plane that
    wanders by up to ``wander`` (x, y) metres around the origin, rolled by up to ``roll``
    radians. Plane y is the image's up at zero roll. Poses are ``T_plane_camera``.
    """
    eye = SinePath.random(rng, (0.0, 0.0, (near + far) / 2), (*lateral, (far - near) / 2), PERIOD_RANGE_S)
    target = SinePath.random(rng, (0.0, 0.0, 0.0), (*wander, 0.0), PERIOD_RANGE_S)
    return LookAtPath(eye, target, SinePath.random(rng, (0.0,), (roll,), PERIOD_RANGE_S), np.array([0.0, 1.0, 0.0]))
