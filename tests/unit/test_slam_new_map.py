"""A young map given up: the constant-velocity extrapolation and the ``Anchor`` that places the next map."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from services.geometry.se3 import invert, make_transform
from services.slam.frontend import Anchor, extrapolated


def motion(rotvec: tuple[float, float, float], translation: tuple[float, float, float]) -> np.ndarray:
    return make_transform(Rotation.from_rotvec(rotvec).as_matrix(), np.array(translation, float))


START = motion((0.1, -0.2, 0.05), (1.0, 2.0, -0.5))
STEP = motion((0.0, 0.02, 0.0), (0.0, 0.0, -1.1))
"""``T_current_previous`` of a camera driving forward (camera z) and turning a little, over 0.1 s."""


def test_one_step_on_is_the_step_itself():
    assert extrapolated(START, (STEP, 0.1), 0.1) == pytest.approx(STEP @ START, abs=1e-12)


@pytest.mark.parametrize("seconds", [0.05, 0.3, -0.1])
def test_the_step_scales_as_scipy_scales_its_rotation_vector(seconds):
    carried = extrapolated(START, (STEP, 0.1), seconds)
    ratio = seconds / 0.1
    rotation = Rotation.from_matrix(STEP[:3, :3]).as_rotvec() * ratio
    assert carried @ invert(START) == pytest.approx(motion(tuple(rotation), tuple(STEP[:3, 3] * ratio)), abs=1e-12)


def test_the_anchor_places_a_pair_where_the_motion_carries_the_camera_at_its_speed():
    anchor = Anchor(START, 1_000_000_000, (STEP, 0.1), speed=11.0)
    placed = anchor.place(1_300_000_000, 1_600_000_000, baseline=0.5)
    assert placed is not None
    T_first, scale = placed
    assert T_first == pytest.approx(extrapolated(START, (STEP, 0.1), 0.3), abs=1e-12)
    assert scale * 0.5 == pytest.approx(11.0 * 0.3)


def test_without_a_motion_the_pair_starts_at_the_last_pose():
    placed = Anchor(START, 0, None, speed=2.0).place(100_000_000, 200_000_000, baseline=1.0)
    assert placed is not None and np.array_equal(placed[0], START) and placed[1] == pytest.approx(0.2)


@pytest.mark.parametrize(("speed", "second_ns", "baseline"), [(float("nan"), 2, 1.0), (0.0, 2, 1.0), (3.0, 1, 1.0),
                                                              (3.0, 2, 0.0)])
def test_no_place_without_a_speed_a_time_span_or_a_baseline(speed, second_ns, baseline):
    assert Anchor(START, 0, (STEP, 0.1), speed).place(1, second_ns, baseline) is None
