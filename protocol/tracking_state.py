"""Where a tracker stands for one target: the one vocabulary of tracking states.

Trackers' algorithms report in it and poses carry it (``Pose.state``, ``RigidBody.state``). It imports
nothing but the standard library, so that algorithm modules, which never touch the wire, may use it
too (``tests/unit/test_layers.py``). Why a tracker has no pose, or why it is still initialising, is
not a state of its own: it travels as ``Pose.reason`` (``too_few_matches``, ``low_parallax``, ...).
"""

from __future__ import annotations

from enum import StrEnum

__all__ = ["TrackingState"]


class TrackingState(StrEnum):
    """Where a tracker stands for one target."""

    TRACKING = "tracking"
    """A fresh estimate from this frame's measurements."""
    RECOGNISED = "recognised"
    """A fresh estimate from this frame's measurements, found from scratch (a natural-feature target
    recognised by its descriptors) rather than followed on from the previous frame."""
    PREDICTED = "predicted"
    """No measurement in this frame; the pose is carried over or predicted."""
    INITIALISING = "initialising"
    """No pose yet: the tracker is still building what it tracks against (SLAM's first map, or its
    metric anchor); ``Pose.reason`` says what it waits for."""
    LOST = "lost"
    """No pose; ``Pose.reason`` may say why."""
    NO_CALIBRATION = "no_calibration"
    """The camera has no calibration, so no metric pose can be given."""
