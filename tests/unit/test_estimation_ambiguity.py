"""Ambiguity tracker: the ratio test, the anchored track's choice, the prior's age limit, and no
propagation of guesses (a choice by lower error in an ambiguous view anchors nothing)."""

import numpy as np
import pytest

from services.estimation.markers.ambiguity import AmbiguityTracker
from services.geometry.planar_pnp import Candidate
from services.geometry.rotation import matrix_from_rotvec
from services.geometry.se3 import make_transform

RIGHT = make_transform(matrix_from_rotvec([0.3, 0.0, 0.0]), [0.0, 0.0, 0.5])
FLIP = make_transform(matrix_from_rotvec([-0.3, 0.0, 0.0]), [0.0, 0.0, 0.5])
"""The two poses of a planar target: the true one and its flip about the line of sight."""


def pair(right_rms: float, flip_rms: float) -> list[Candidate]:
    """The two candidates, lowest RMS first."""
    return sorted([Candidate(RIGHT, right_rms), Candidate(FLIP, flip_rms)], key=lambda c: c.rms_px)


def frame(tracker: AmbiguityTracker, target: str, candidates: list[Candidate]) -> tuple[np.ndarray, bool, bool]:
    """One frame of one target, as the estimator runs it: the pose chosen, whether the view was
    ambiguous, and whether the choice is anchored (recorded as the target's track)."""
    tracker.next_frame()
    ambiguous = tracker.is_ambiguous(candidates)
    chosen, anchored = tracker.choose(target, candidates if ambiguous else candidates[:1], ambiguous)
    tracker.record(target, chosen.T, anchored)
    return chosen.T, ambiguous, anchored


def test_the_ratio_test():
    tracker = AmbiguityTracker(ratio=2.0)
    assert tracker.is_ambiguous(pair(0.5, 0.9))
    assert not tracker.is_ambiguous(pair(0.5, 1.0))
    assert not tracker.is_ambiguous(pair(0.5, 0.9)[:1])
    assert not AmbiguityTracker(ratio=1.0).is_ambiguous(pair(0.5, 0.6))


def test_without_a_track_the_lower_error_wins_and_anchors_only_when_unambiguous():
    tracker = AmbiguityTracker()
    assert tracker.track("a") is None
    T, ambiguous, anchored = frame(tracker, "a", pair(0.6, 0.5))
    assert ambiguous and not anchored and T is FLIP
    T, ambiguous, anchored = frame(tracker, "b", pair(0.1, 5.0))
    assert not ambiguous and anchored and T is RIGHT


def test_an_ambiguous_view_follows_the_anchored_track_against_the_lower_error():
    tracker = AmbiguityTracker()
    frame(tracker, "a", pair(0.1, 5.0))
    T, ambiguous, anchored = frame(tracker, "a", pair(0.6, 0.5))
    assert ambiguous and anchored and T is RIGHT
    T, _, anchored = frame(tracker, "a", pair(0.7, 0.4))
    assert anchored and T is RIGHT  # chosen by an anchored track: anchored in turn
    assert tracker.track("a").anchored and tracker.track("a").frame == 3


def test_a_track_older_than_prior_max_age_is_ignored():
    tracker = AmbiguityTracker(prior_max_age=2)
    frame(tracker, "a", pair(0.1, 5.0))
    tracker.next_frame()
    T, _, anchored = frame(tracker, "a", pair(0.6, 0.5))  # two frames old: followed
    assert anchored and T is RIGHT
    for _ in range(2):
        tracker.next_frame()
    T, ambiguous, anchored = frame(tracker, "a", pair(0.6, 0.5))  # three frames old: not
    assert ambiguous and not anchored and T is FLIP


def test_a_guess_does_not_propagate():
    """The lower error of an ambiguous first view (here the flip) must not decide the next ambiguous
    views, nor anchor them."""
    tracker = AmbiguityTracker()
    T, _, anchored = frame(tracker, "a", pair(0.6, 0.5))
    assert T is FLIP and not anchored and not tracker.track("a").anchored
    T, _, anchored = frame(tracker, "a", pair(0.5, 0.6))
    assert T is RIGHT and not anchored
    T, _, anchored = frame(tracker, "a", pair(0.6, 0.5))
    assert T is FLIP and not anchored


def test_tracks_are_per_target_and_reset_forgets_them():
    tracker = AmbiguityTracker()
    frame(tracker, "a", pair(0.1, 5.0))
    T, _, anchored = frame(tracker, "b", pair(0.6, 0.5))
    assert T is FLIP and not anchored
    tracker.reset()
    assert tracker.track("a") is None
    T, _, anchored = frame(tracker, "a", pair(0.6, 0.5))
    assert T is FLIP and not anchored


def test_bad_arguments_are_refused():
    with pytest.raises(ValueError, match="ratio"):
        AmbiguityTracker(ratio=0.5)
    with pytest.raises(ValueError, match="prior_max_age"):
        AmbiguityTracker(prior_max_age=-1)
