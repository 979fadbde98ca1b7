"""Marker distances without range bias on a blurred, noisy, unevenly lit sequence (``marker_range``).

Requirement, on AprilTag 36h11 and ArUco 4x4 markers alike (the sequence of ``marker_range``:
two 55 mm markers 0.3-1.0 m away, blur, noise, changing light): every side of the default corners
sits on the true edge (|median offset along its outward normal| <= ``MAX_SIDE_BIAS_PX``, at every
distance), and the default poses' median rotation error <= ``MAX_ROTATION_DEG`` and median
translation error and |median signed range error| <= ``MAX_DISTANCE_PCT`` of the distance, every
view the truth lists found. Against AprilTag 3 (``pupil_apriltags``, the dev extra) on the same
AprilTag frames: at least as accurate in rotation and in distance; skipped, with the reason,
where it does not import.

``python -m tests.accuracy.marker_range`` prints the figures (docs/accuracy.md has them).
"""

import functools
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.accuracy.marker_range import FAMILIES, NOT_INSTALLED, Scores, artrack, score, sequence

ROOT = Path(__file__).resolve().parents[2]

pytestmark = pytest.mark.slow

MAX_SIDE_BIAS_PX = 0.05
MAX_ROTATION_DEG = 0.12
MAX_DISTANCE_PCT = 0.12


@functools.cache
def results(dictionary: str) -> tuple[list, np.ndarray, Scores]:
    """The sequence of ``dictionary``'s frames, its camera matrix and artrack's scores on it."""
    scene, frames = sequence(dictionary)
    K = scene.cameras[0].K
    return frames, K, score(frames, K, artrack(dictionary, K))


@pytest.mark.parametrize("dictionary", FAMILIES)
def test_every_side_sits_on_its_edge_at_every_distance(dictionary):
    _, _, ours = results(dictionary)
    assert np.all(np.abs(np.median(ours.normal_px, axis=0)) <= MAX_SIDE_BIAS_PX)
    assert np.all(np.abs(np.median(ours.along_px, axis=0)) <= MAX_SIDE_BIAS_PX)
    for near, far in ((0.3, 0.55), (0.55, 0.75), (0.75, 1.05)):
        at = (ours.distance_m >= near) & (ours.distance_m < far)
        assert at.sum() >= 20, (near, far)
        assert abs(np.median(ours.normal_px[at])) <= MAX_SIDE_BIAS_PX, (near, far)


@pytest.mark.parametrize("dictionary", FAMILIES)
def test_poses_reach_the_rotation_and_distance_bounds(dictionary):
    _, _, ours = results(dictionary)
    print(f"\n{dictionary}: {ours.summary()}")
    assert len(ours.distance_m) == ours.truth_views >= 280
    assert np.median(ours.rotation_deg) <= MAX_ROTATION_DEG
    assert np.median(ours.translation_pct) <= MAX_DISTANCE_PCT
    assert abs(np.median(ours.range_pct)) <= MAX_DISTANCE_PCT


def apriltag3_medians() -> dict:
    """AprilTag 3's medians on the AprilTag sequence, computed in a process of its own (``marker_range``'s
    docstring says why); run again once when that process dies of a signal, skipped if it dies twice."""
    signals = []
    for _ in range(2):
        done = subprocess.run([sys.executable, "-m", "tests.accuracy.marker_range", "apriltag3"], cwd=ROOT,
                              capture_output=True, text=True, timeout=900)
        if done.returncode == NOT_INSTALLED:
            pytest.skip("pupil_apriltags (AprilTag 3) is not installed: pip install -e '.[dev]'")
        if done.returncode >= 0:
            assert done.returncode == 0, done.stderr[-2000:]
            return json.loads(done.stdout.strip().splitlines()[-1])
        signals.append(-done.returncode)
    pytest.skip(f"AprilTag 3 died of signal {signals} in both runs: pupil-apriltags corrupts its heap now and then "
                "(pupil-labs/apriltags#39)")


@pytest.mark.integration
def test_at_least_as_accurate_as_apriltag_3():
    _, _, ours = results("DICT_APRILTAG_36h11")
    theirs = apriltag3_medians()
    print(f"\nAprilTag 3: {theirs}")
    assert theirs["views"] >= 0.95 * theirs["truth_views"]
    assert np.median(ours.rotation_deg) <= theirs["rotation_deg"]
    assert np.median(ours.translation_pct) <= theirs["translation_pct"]
