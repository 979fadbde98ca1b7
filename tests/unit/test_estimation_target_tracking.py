"""Incremental tracking of an image target, scored against the ``planar_target`` scene's ground truth.

Every second of the first 150 frames is tracked, and recognised alone, with the target built from the
scene's own texture. Run with ``-s`` to print the figures (docs/feature-targets.md quotes them).
"""

import time

import numpy as np
import pytest

from protocol.tracking_state import TrackingState
from services.estimation.targets.features import make_extractor
from services.estimation.targets.recognition import TargetRecognizer
from services.estimation.targets.target import build_target
from services.estimation.targets.tracking import (
    FrameFeatures,
    TargetTracker,
    TrackingOptions,
    track_targets,
)
from services.geometry.evaluation import pose_error
from services.synthetic import make_scene
from services.synthetic.texture import procedural_texture

FRAMES = range(0, 150, 2)
FPS = 30.0


def stamp(index: int) -> int:
    return round(index * 1e9 / FPS)


@pytest.fixture(scope="module")
def scene():
    return make_scene("planar_target")


@pytest.fixture(scope="module")
def frames(scene):
    return [scene.render(i) for i in FRAMES]


@pytest.fixture(scope="module")
def target(scene):
    return build_target("poster", scene.texture, scene.size_m[0])


def errors(poses, frames):
    """(rotation errors deg, translation errors % of distance) of (4, 4) poses against the frames' truth."""
    rotation, translation = [], []
    for T, frame in zip(poses, frames, strict=True):
        (_, _, T_true), = frame.truth["cam0"]
        angle, distance = pose_error(T, T_true)
        rotation.append(np.degrees(angle))
        translation.append(100 * distance / np.linalg.norm(T_true[:3, 3]))
    return np.array(rotation), np.array(translation)


def track(tracker, frames, K):
    poses, seconds = [], []
    for frame in frames:
        start = time.perf_counter()
        poses.append(tracker.track(frame.images["cam0"], K, None, stamp(frame.index)))
        seconds.append(time.perf_counter() - start)
    return poses, np.array(seconds)


def summary(name, rotation, translation, seconds):
    return (f"{name}: rotation median {np.median(rotation):.3f} deg (p90 {np.percentile(rotation, 90):.3f}), "
            f"translation median {np.median(translation):.3f} % (p90 {np.percentile(translation, 90):.3f}), "
            f"{1e3 * np.median(seconds):.1f} ms a frame")


@pytest.mark.slow
def test_tracking_is_never_lost_and_at_least_as_accurate_as_recognition_alone(scene, frames, target):
    K = scene.cameras[0].K
    poses, tracked_s = track(TargetTracker(target), frames, K)
    assert all(p.posed for p in poses), [(f.index, p.reason) for f, p in zip(frames, poses, strict=True)
                                         if not p.posed]
    states = [p.state for p in poses]
    recognised = states.count(TrackingState.RECOGNISED)
    assert states[0] is TrackingState.RECOGNISED and recognised <= 2
    recognizer, extract = TargetRecognizer(target), make_extractor(target.detector)
    alone, recognised_s = [], []
    for frame in frames:
        start = time.perf_counter()
        result = recognizer.recognise_image(frame.images["cam0"], K, None, extract)
        recognised_s.append(time.perf_counter() - start)
        assert result.recognised
        alone.append(result.T_camera_target)
    tracking = errors([p.T_camera_target for p in poses], frames)
    recognition = errors(alone, frames)
    tracked = np.array([s is TrackingState.TRACKING for s in states])
    print(f"\n{len(frames)} frames, {recognised} recognised, {tracked.sum()} tracked")
    print(summary("tracking", *tracking, tracked_s[tracked]))
    print(summary("recognition", *recognition, np.array(recognised_s)))
    assert np.median(tracking[0]) <= np.median(recognition[0])
    assert np.median(tracking[1]) <= np.median(recognition[1])
    assert all(p.inliers >= TrackingOptions().min_points and p.rms_px <= 1.0 for p in poses[1:])
    assert all(p.covariance.shape == (6, 6) and np.all(np.linalg.eigvalsh(p.covariance) > 0) for p in poses)


@pytest.mark.slow
def test_alignment_refines_the_tracked_pose(scene, frames, target):
    K = scene.cameras[0].K
    some = frames[:40]
    plain, plain_s = track(TargetTracker(target), some, K)
    aligned, aligned_s = track(TargetTracker(target, TrackingOptions(align=True)), some, K)
    assert all(p.posed for p in plain + aligned)
    without = errors([p.T_camera_target for p in plain], some)
    with_alignment = errors([p.T_camera_target for p in aligned], some)
    print(f"\n{len(some)} frames\n{summary('without alignment', *without, plain_s)}\n"
          f"{summary('with alignment', *with_alignment, aligned_s)}")
    for aligned_errors, plain_errors in zip(with_alignment, without, strict=True):
        assert np.median(aligned_errors) <= np.median(plain_errors)
        assert np.percentile(aligned_errors, 90) < 0.8 * np.percentile(plain_errors, 90)


def test_a_covered_frame_is_lost_and_the_target_recognised_when_it_returns(scene, frames, target):
    K = scene.cameras[0].K
    tracker = TargetTracker(target)
    blank = np.full_like(frames[0].images["cam0"], 110)
    states, reasons = [], []
    sequence = [(f.images["cam0"], f.index) for f in frames[:4]] + [(blank, 8)] \
        + [(f.images["cam0"], f.index) for f in frames[5:8]]
    for image, index in sequence:
        pose = tracker.track(image, K, None, stamp(index))
        states.append(pose.state)
        reasons.append(pose.reason)
    assert states == [TrackingState.RECOGNISED, *[TrackingState.TRACKING] * 3, TrackingState.LOST,
                      TrackingState.RECOGNISED, TrackingState.TRACKING, TrackingState.TRACKING]
    assert reasons[4] == "no_features" and reasons[5] == ""


def test_several_targets_share_one_extraction_a_frame(scene, frames, target):
    calls = []
    extract = make_extractor("orb")

    def counted(grey):
        calls.append(1)
        return extract(grey)

    other = build_target("other", procedural_texture(np.random.default_rng(7), 800, 600), 0.3)
    trackers = [TargetTracker(target, extract=counted), TargetTracker(other, extract=counted)]
    K = scene.cameras[0].K
    for frame in frames[:6]:
        poses = track_targets(trackers, frame.images["cam0"], K, None, stamp(frame.index))
        assert poses[0].posed and poses[1].state is TrackingState.LOST
    assert len(calls) == 6
    features = FrameFeatures(frames[0].images["cam0"], counted)
    assert len(calls) == 6  # nothing extracted until asked
    assert features.get() is features.get() and len(calls) == 7


@pytest.mark.parametrize("options", [{"measure": {"window_px": 4}}, {"measure": {"window_px": 14}}, {"min_points": 3},
                                     {"refill_below": 1000}, {"measure": {"forward_backward_px": 0}},
                                     {"anchor_every": -1}, {"measure": {"levels": 9}}])
def test_bad_options_are_refused(options):
    with pytest.raises(ValueError):
        TrackingOptions(**options)
