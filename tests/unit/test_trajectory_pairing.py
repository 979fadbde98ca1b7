"""Pairing an estimate with the truth by stamp, frame number or index, and the refusal of trajectories
that hardly overlap; the real KITTI excerpt scored from a frame other than its first."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from services.geometry.evaluation import Similarity, apply_similarity
from services.geometry.se3 import make_transform
from services.recorder.pairing import pair, pairs_needed
from services.recorder.scoring import evaluate, format_evaluation
from services.recorder.trajectories import Trajectory, TrajectoryError, read_kitti
from tests.data import data_dir

KITTI_DATA = "vo_kitti_odometry_seq06_frames000-050"
WALL_NS = 1_700_000_000_000_000_000
STEP_NS = 100_000_000


def walk(n: int) -> np.ndarray:
    """(n, 4, 4) poses 1 m apart along x, turning 4 degrees about y at each step."""
    return np.array([make_transform(Rotation.from_euler("y", 4 * i, degrees=True).as_matrix(),
                                    [float(i), 0.1 * i * i, 0.0]) for i in range(n)])


def test_frame_numbers_pair_an_estimate_that_starts_late_with_its_own_frames():
    gt = Trajectory(walk(20), None, "gt", np.arange(20))
    est = Trajectory(walk(20)[3:], WALL_NS + STEP_NS * np.arange(17), "est", np.arange(3, 20))
    pairing = pair(est, gt)
    assert pairing.by == "frame" and pairing.note == ""
    assert pairing.rows.tolist() == [[k, k + 3] for k in range(17)]
    assert evaluate(est, gt).score.ate.stats.max < 1e-9


def test_stamps_come_first_and_frame_numbers_take_over_when_the_clocks_differ():
    poses = walk(12)
    frames = np.arange(12)
    gt = Trajectory(poses, STEP_NS * frames, "gt", frames)  # KITTI times: seconds from the start
    same_clock = Trajectory(poses[2:], STEP_NS * frames[2:] + 1_000_000, "est", frames[:10])
    by_stamp = pair(same_clock, gt, max_dt_ns=2_000_000)
    assert by_stamp.by == "stamp" and by_stamp.rows.tolist() == [[k, k + 2] for k in range(10)]
    wall_clock = Trajectory(poses[2:], WALL_NS + STEP_NS * frames[2:], "est", frames[2:])
    by_frame = pair(wall_clock, gt, max_dt_ns=2_000_000)
    assert by_frame.by == "frame" and by_frame.rows.tolist() == [[k, k + 2] for k in range(10)]
    with pytest.raises(TrajectoryError, match=r"hardly overlap: 0 paired by stamp within 0.002 s, at least 5 needed"):
        pair(wall_clock, gt, "stamp", 2_000_000)


def test_without_stamps_or_frame_numbers_on_both_sides_only_equal_counts_pair_by_index_and_say_so():
    tum = Trajectory(walk(8), WALL_NS + STEP_NS * np.arange(8), "est.tum")
    kitti = Trajectory(walk(8), None, "poses.txt", np.arange(8))
    pairing = pair(tum, kitti)
    assert pairing.by == "index" and pairing.rows.tolist() == [[i, i] for i in range(8)]
    assert pairing.note == ("est.tum has stamps but no frame numbers, poses.txt frame numbers but no stamps: "
                            "row i of each taken as the same instant")
    assert pairing.note in format_evaluation(evaluate(tum, kitti))
    late = Trajectory(walk(8)[2:], WALL_NS + STEP_NS * np.arange(6), "est.tum")
    with pytest.raises(TrajectoryError, match=r"nothing to pair est\.tum \(6 poses\) and poses\.txt \(8 poses\) by: "
                                              r"est\.tum has stamps but no frame numbers, .* their counts differ"):
        pair(late, kitti)
    assert pair(late, kitti, "index").rows.tolist() == [[i, i] for i in range(6)]  # asked for: done
    with pytest.raises(TrajectoryError, match="cannot pair by frame number: est.tum has stamps but no frame numbers"):
        pair(late, kitti, "frame")
    with pytest.raises(TrajectoryError, match="cannot pair by stamp: poses.txt has frame numbers but no stamps"):
        pair(late, kitti, "stamp")


def test_trajectories_that_hardly_overlap_are_refused_with_their_counts():
    gt = Trajectory(walk(51), None, "poses.txt", np.arange(51))
    other = Trajectory(walk(232), WALL_NS + STEP_NS * np.arange(232), "other.mcap", np.arange(232))
    with pytest.raises(TrajectoryError, match=r"^other\.mcap \(232 poses\) and poses\.txt \(51 poses\) hardly overlap: "
                                              r"51 paired by frame number, at least 116 needed \(half the estimate's "
                                              r"poses, and no fewer than 3\)$"):
        pair(other, gt)
    with pytest.raises(TrajectoryError, match="51 paired by index, at least 116 needed"):
        pair(other, gt, "index")
    two = Trajectory(walk(2), None, "two.txt", np.arange(2))
    assert pairs_needed(two) == 3
    with pytest.raises(TrajectoryError, match="2 paired by frame number, at least 3 needed"):
        pair(two, gt)
    half = Trajectory(walk(10), None, "half.txt", np.arange(46, 56))  # frames 46-55 against 0-50: 5 of 10
    assert pair(half, gt).rows.tolist() == [[k, 46 + k] for k in range(5)]


def test_a_frame_number_twice_pairs_once():
    gt = Trajectory(walk(6), None, "gt", np.arange(6))
    est = Trajectory(walk(6)[[1, 1, 2, 3, 4]], None, "est", np.array([1, 1, 2, 3, 4]))
    assert pair(est, gt).rows.tolist() == [[0, 1], [2, 2], [3, 3], [4, 4]]


def test_the_real_kitti_truth_scores_an_estimate_of_frames_2_to_50_by_frame_number():
    gt = read_kitti(data_dir(KITTI_DATA) / "poses.txt")
    assert gt.stamps_ns is None and gt.frames.tolist() == list(range(51))
    similarity = Similarity(Rotation.from_rotvec([0.2, -0.1, 0.3]).as_matrix(), np.array([1.0, 2.0, -3.0]), 0.2)
    est = Trajectory(apply_similarity(similarity, gt.poses[2:]), WALL_NS + STEP_NS * np.arange(2, 51), "slam",
                     np.arange(2, 51))
    evaluation = evaluate(est, gt, align="sim3")
    assert evaluation.pairing.by == "frame" and len(evaluation.pairs) == 49
    assert evaluation.score.ate.stats.max < 1e-6 and evaluation.score.ate.alignment.s == pytest.approx(5.0)
    assert "matched      49 poses (49 estimated, 51 true) by frame number" in format_evaluation(evaluation)
    metric = Trajectory(gt.poses[2:], est.stamps_ns, "slam", est.frames)
    assert evaluate(metric, gt, align="none").score.ate.stats.max < 1e-12
    shifted = evaluate(metric, gt, align="none", by="index")  # row order alone pairs frame k + 2 with frame k
    assert shifted.score.ate.stats.rmse > 2.0  # the car drives 1.2 m a frame
