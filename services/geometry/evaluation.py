"""Scoring estimated poses against ground truth, in the field's terms.

Poses are (4, 4) ``T_a_b`` of the same two frames; rotation errors are radians, translation
errors metres (callers convert to degrees, millimetres or % of distance for reports).
"""

from __future__ import annotations

import numpy as np

from services.geometry.rotation import rotation_angle


def pose_error(T_est: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    """``(rotation error rad, translation error m)`` of an estimate ``T_a_b`` against the true ``T_a_b``.

    The rotation error is the angle of ``R_est^T R_true``; the translation error is the distance
    between the two origins of frame b expressed in frame a.
    """
    T_est, T_true = np.asarray(T_est, dtype=np.float64), np.asarray(T_true, dtype=np.float64)
    return rotation_angle(T_est[:3, :3], T_true[:3, :3]), float(np.linalg.norm(T_est[:3, 3] - T_true[:3, 3]))
