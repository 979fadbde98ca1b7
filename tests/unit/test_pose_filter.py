"""The One Euro pose filter: a still target's tracked pose shakes less, a moving one's does not lag.

Poses come from the target tracker on ``planar_target`` with image noise (2 grey levels): 60 frames of
a still camera (``motion=static``) for the jitter, 90 of the swaying one for the lag. Run with ``-s``
to print the figures (docs/feature-targets.md quotes them).
"""

import numpy as np
import pytest

from services.estimation.pose_filter import OneEuroOptions, OneEuroPoseFilter
from services.estimation.targets.target import build_target
from services.estimation.targets.tracking import TargetTracker
from services.geometry.evaluation import pose_error
from services.geometry.rotation import matrix_from_rotvec
from services.geometry.se3 import make_transform
from services.synthetic import make_scene

FPS = 30.0
SETTLE = 10
"""Frames the filter is given to settle before jitter is measured."""


def stamp(index: int) -> int:
    return round(index * 1e9 / FPS)


def tracked(motion: str, count: int):
    """(raw poses, filtered poses, true poses) of ``count`` frames of ``planar_target`` with ``motion``."""
    scene = make_scene("planar_target", motion=motion, noise_std=2.0)
    K = scene.cameras[0].K
    tracker = TargetTracker(build_target("poster", scene.texture, scene.size_m[0]))
    smooth = OneEuroPoseFilter()
    raw, filtered, truth = [], [], []
    for index in range(count):
        frame = scene.render(index)
        pose = tracker.track(frame.images["cam0"], K, None, stamp(index))
        assert pose.posed
        raw.append(pose.T_camera_target)
        filtered.append(smooth(stamp(index), pose.T_camera_target))
        truth.append(frame.truth["cam0"][0][2])
    return raw, filtered, truth


def jitter(poses):
    """(rotation deg, translation mm): RMS of the frame-to-frame pose changes."""
    steps = np.array([pose_error(b, a) for a, b in zip(poses[:-1], poses[1:], strict=True)])
    return np.degrees(np.sqrt(np.mean(steps[:, 0] ** 2))), 1e3 * np.sqrt(np.mean(steps[:, 1] ** 2))


def median_errors(poses, truth):
    """(rotation deg, translation mm): median errors against the truth."""
    errors = np.array([pose_error(T, T_true) for T, T_true in zip(poses, truth, strict=True)])
    return np.degrees(np.median(errors[:, 0])), 1e3 * np.median(errors[:, 1])


@pytest.mark.slow
def test_the_filter_stills_a_static_target():
    raw, filtered, _ = tracked("static", 60)
    before, after = jitter(raw[SETTLE:]), jitter(filtered[SETTLE:])
    print(f"\nstatic jitter, frame to frame RMS: raw {before[0]:.4f} deg {before[1]:.4f} mm, "
          f"filtered {after[0]:.4f} deg {after[1]:.4f} mm")
    assert after[0] < before[0] / 2.5 and after[1] < before[1] / 2


@pytest.mark.slow
def test_the_filter_does_not_lag_on_motion():
    """What the filter adds to the error on motion is under 2 % of a frame's motion: it trails by
    less than a fiftieth of a frame (a plain low-pass at its 0.5 Hz cut-off would trail by about ten)."""
    raw, filtered, truth = tracked("sway", 90)
    before, after = median_errors(raw, truth), median_errors(filtered, truth)
    steps = np.array([pose_error(b, a) for a, b in zip(truth[:-1], truth[1:], strict=True)])
    step_deg, step_mm = np.degrees(np.median(steps[:, 0])), 1e3 * np.median(steps[:, 1])
    print(f"\nmoving ({step_deg:.2f} deg, {step_mm:.2f} mm a frame), median error against the truth: raw "
          f"{before[0]:.4f} deg {before[1]:.4f} mm, filtered {after[0]:.4f} deg {after[1]:.4f} mm")
    assert after[0] - before[0] < 0.02 * step_deg and after[1] - before[1] < 0.02 * step_mm


def test_without_beta_the_lag_is_a_first_order_low_pass_one():
    """At constant velocity v a first-order low-pass at fc trails by v / (2 pi fc)."""
    lagging = OneEuroPoseFilter(OneEuroOptions(beta=0.0, rotation_beta=0.0))
    errors = []
    for index in range(60):
        T = make_transform(matrix_from_rotvec([0.0, 0.01 * index, 0.0]), [0.003 * index, 0.0, 0.5])
        angle, distance = pose_error(lagging(stamp(index), T), T)
        errors.append((angle, distance))
    angle, distance = errors[-1]
    tau = 1 / (2 * np.pi * OneEuroOptions().min_cutoff_hz)
    assert angle == pytest.approx(0.01 * FPS * tau, rel=0.1) and distance == pytest.approx(0.003 * FPS * tau, rel=0.1)


def test_the_first_pose_passes_and_a_gap_restarts():
    smooth = OneEuroPoseFilter()
    T0 = make_transform(np.eye(3), [0.0, 0.0, 0.5])
    T1 = make_transform(matrix_from_rotvec([0.0, 0.0, 0.3]), [0.1, 0.0, 0.5])
    np.testing.assert_array_equal(smooth(0, T0), T0)
    assert pose_error(smooth(stamp(1), T1), T1)[1] > 0
    np.testing.assert_allclose(smooth(stamp(1) + 10**9, T1), T1)
    with pytest.raises(ValueError, match="not after"):
        smooth(0, T1)


@pytest.mark.parametrize("options", [{"min_cutoff_hz": 0.0}, {"beta": -1.0}, {"derivative_cutoff_hz": float("nan")},
                                     {"max_gap_s": 0}])
def test_bad_options_are_refused(options):
    with pytest.raises(ValueError):
        OneEuroOptions(**options)
