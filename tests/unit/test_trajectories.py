"""Trajectory files (TUM, KITTI, recordings) read back, bad ones refused naming file and line, and the
real ground-truth files scored against perturbed copies of themselves."""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from protocol import FrameTransform, GroundTruth, Header, Pose, encode
from protocol.spatial import Transform
from protocol.tracking_state import TrackingState
from services.geometry.evaluation import Similarity, apply_similarity
from services.geometry.se3 import make_transform
from services.recorder.export import ExportError
from services.recorder.pairing import pair
from services.recorder.scoring import evaluate, format_evaluation
from services.recorder.trajectories import (
    Trajectory,
    TrajectoryError,
    load_trajectory,
    read_kitti,
    read_tum,
    text_format,
)
from services.recorder.writing import RecordingWriter
from tests.data import data_dir

TUM_DATA = "tum_rgbd_fr3_long_office_household_1hz"
KITTI_DATA = "vo_kitti_odometry_seq06_frames000-050"


def write_tum(path: Path, stamps_ns: np.ndarray, poses: np.ndarray) -> Path:
    lines = ["# timestamp tx ty tz qx qy qz qw"]
    for stamp, T in zip(stamps_ns, poses, strict=True):
        q = Rotation.from_matrix(T[:3, :3]).as_quat()
        lines.append(f"{stamp // 10**9}.{stamp % 10**9:09d} " + " ".join(repr(float(v)) for v in [*T[:3, 3], *q]))
    path.write_text("\n".join(lines) + "\n")
    return path


def write_kitti(path: Path, poses: np.ndarray) -> Path:
    path.write_text("".join(" ".join(f"{v:.12e}" for v in T[:3].ravel()) + "\n" for T in poses))
    return path


def test_tum_files_read_exact_stamps_skip_comments_and_take_commas(tmp_path):
    path = tmp_path / "t.txt"
    path.write_text("# a comment\n\n1341847980.7230 1 2 3 0 0 0 1\n"
                    "1341847980.733000001,1.5,2,3,0,0,0.6,0.8\n  # indented comment\n")
    trajectory = read_tum(path)
    assert trajectory.stamps_ns.tolist() == [1341847980723000000, 1341847980733000001]
    assert np.allclose(trajectory.poses[1], make_transform(Rotation.from_quat([0, 0, 0.6, 0.8]).as_matrix(),
                                                           [1.5, 2, 3]))
    assert text_format(path) == "tum" and load_trajectory(path).stamps_ns.tolist() == trajectory.stamps_ns.tolist()


@pytest.mark.parametrize(("text", "message"), [
    ("1 2 3 4 0 0 0 1\n1 2 3\n", r"t\.txt:2: a TUM file \(stamp tx ty tz qx qy qz qw\) needs 8 numbers a line, "
                                  "found 3"),
    ("1 2 3 4 0 0 0 1\n\n1 2 x 4 0 0 0 1\n", r"t\.txt:3: not a number: 'x'"),
    ("1 2 3 4 0 0 0 2\n", r"t\.txt:1: quaternion \(qx qy qz qw\) has norm 2, not 1"),
    ("1 2 3 4 0 0 0 nan\n", r"t\.txt:1: numbers must be finite"),
    ("# nothing\n", r"t\.txt holds no poses"),
])
def test_bad_tum_files_give_one_error_naming_file_and_line(tmp_path, text, message):
    path = tmp_path / "t.txt"
    path.write_text(text)
    with pytest.raises(TrajectoryError, match=message):
        read_tum(path)


def test_kitti_files_read_row_major_poses_numbered_by_frame_without_stamps(tmp_path):
    rng = np.random.default_rng(0)
    poses = np.array([make_transform(Rotation.random(random_state=i).as_matrix(), rng.normal(0, 3, 3))
                      for i in range(5)])
    path = write_kitti(tmp_path / "k.txt", poses)
    trajectory = load_trajectory(path)
    assert trajectory.stamps_ns is None and np.allclose(trajectory.poses, poses, atol=1e-11)
    assert trajectory.frames.tolist() == [0, 1, 2, 3, 4]
    bad = tmp_path / "bad.txt"
    bad.write_text(path.read_text() + "1 0 0 0 0 2 0 0 0 0 1 0\n")
    with pytest.raises(TrajectoryError, match=r"bad\.txt:6: the 3x3 part is not a rotation"):
        read_kitti(bad)


def test_a_kitti_times_file_beside_the_poses_gives_their_stamps(tmp_path, caplog):
    path = write_kitti(tmp_path / "poses.txt", np.repeat(np.eye(4)[None], 3, axis=0))
    (tmp_path / "times.txt").write_text("0.000000e+00\n1.036224e-01\n2.072448e-01\n")
    trajectory = read_kitti(path)
    assert trajectory.stamps_ns.tolist() == [0, 103_622_400, 207_244_800] and trajectory.frames.tolist() == [0, 1, 2]
    (tmp_path / "times.txt").write_text("0.0\n0.1\n")
    assert read_kitti(path).stamps_ns is None
    assert f"{tmp_path / 'times.txt'} holds 2 stamps for 3 poses: not used" in caplog.text
    (tmp_path / "times.txt").write_text("0.0\n0.1 7\n0.2\n")
    with pytest.raises(TrajectoryError, match=r"times\.txt:2: KITTI times need 1 number a line, found 2"):
        read_kitti(path)
    (tmp_path / "times.txt").write_text("0.0\nsoon\n0.2\n")
    with pytest.raises(TrajectoryError, match=r"times\.txt:2: stamp 'soon' is not a number of seconds"):
        read_kitti(path)


def test_the_format_is_told_by_columns_or_forced(tmp_path):
    seven = tmp_path / "seven.txt"
    seven.write_text("1 2 3 4 5 6 7\n")
    with pytest.raises(TrajectoryError, match=r"seven\.txt:1: 7 columns: neither TUM \(8\) nor KITTI \(12\)"):
        load_trajectory(seven)
    tum = tmp_path / "t.txt"
    tum.write_text("1 2 3 4 0 0 0 1\n")
    with pytest.raises(TrajectoryError, match=r"t\.txt:1: a KITTI pose file .* needs 12 numbers a line, found 8"):
        load_trajectory(tum, "kitti")
    with pytest.raises(TrajectoryError, match="cannot read .*missing.txt: No such file"):
        load_trajectory(tmp_path / "missing.txt")


def recorded_pose(i: int, state: TrackingState = TrackingState.TRACKING) -> Pose:
    return Pose(header=Header(stamp_ns=1_000_000_000 + i * 33_333_333, frame_id="cam0", seq=i),
                child_frame_id="marker/1", state=state,
                transform=Transform(translation=(0.1 * i, 0.0, 1.0), rotation=(0.0, math.sin(i / 20), 0.0,
                                                                                 math.cos(i / 20))))


@pytest.fixture
def recording(tmp_path) -> Path:
    """Poses of ``marker/1`` on ``pose/cam0/marker/1`` (frame 3 lost) and their truth on ``cam0/truth``, rig r."""
    path = tmp_path / "r.mcap"
    writer = RecordingWriter(path, metadata={"namespace": "ar", "rig": "r"})
    for i in range(10):
        pose = recorded_pose(i, TrackingState.LOST if i == 3 else TrackingState.TRACKING)
        truth = GroundTruth(header=pose.header, transforms=(
            FrameTransform(parent_frame="cam0", child_frame="marker/1", transform=recorded_pose(i).transform),
            FrameTransform(parent_frame="cam0", child_frame="marker/2", transform=Transform())))
        writer.write("ar/r/pose/cam0/marker/1", encode(pose), 10 * i)
        writer.write("ar/r/cam0/truth", encode(truth), 10 * i + 1)
    writer.close()
    return path


def test_a_recording_key_reads_as_export_decodes_it_skipping_poses_without_an_estimate(recording):
    est = load_trajectory(recording, key="pose/cam0/marker/1")
    gt = load_trajectory(recording, key="ar/r/cam0/truth", child="marker/1")
    assert len(est) == 9 and len(gt) == 10 and 1_000_000_000 + 3 * 33_333_333 not in est.stamps_ns
    assert np.allclose(est.poses[:, :3, 3], [[0.1 * i, 0, 1] for i in range(10) if i != 3])
    assert est.frames.tolist() == [i for i in range(10) if i != 3] and gt.frames.tolist() == list(range(10))
    for by in ("stamp", "frame"):
        pairs = pair(est, gt, by).rows
        assert pairs.tolist() == [[k, i] for k, i in enumerate(i for i in range(10) if i != 3)]
    assert evaluate(est, gt, max_dt_s=0).score.ate.stats.max < 1e-12
    with pytest.raises(TrajectoryError, match=r"is a recording: name the pose key"):
        load_trajectory(recording)
    with pytest.raises(ExportError, match="carries GroundTruth: choose a child frame with --child"):
        load_trajectory(recording, key="cam0/truth")
    with pytest.raises(ExportError, match="no key 'pose/nobody'"):
        load_trajectory(recording, key="pose/nobody")


def perturbed(poses: np.ndarray, sigma_m: float, similarity: Similarity, seed: int = 0) -> np.ndarray:
    """``similarity`` applied to the poses after Gaussian noise of ``sigma_m`` per axis on their positions."""
    noisy = poses.copy()
    noisy[:, :3, 3] += np.random.default_rng(seed).normal(0, sigma_m, (len(poses), 3))
    return apply_similarity(similarity, noisy)


def check_sim3_figures(est: Trajectory, gt: Trajectory, sigma_m: float, s: float, max_dt_s: float = 0.0) -> None:
    """Sim(3)-aligned ATE about sqrt(3) sigma (less the 7 fitted degrees of freedom), the scale 1/s,
    RPE over one frame about sqrt(6) sigma in translation and nil in rotation."""
    evaluation = evaluate(est, gt, align="sim3", max_dt_s=max_dt_s)
    score, n = evaluation.score, len(gt)
    assert len(evaluation.pairs) == n
    assert score.ate.alignment.s == pytest.approx(1 / s, rel=1e-3)
    assert score.ate.stats.rmse == pytest.approx(sigma_m * math.sqrt((3 * n - 7) / n), rel=0.15)
    assert score.rpe.translation_stats.rmse == pytest.approx(sigma_m * math.sqrt(6), rel=0.15)
    assert score.rpe.rotation_stats.max < 1e-6
    printed = re.search(r"alignment +sim3, scale (\S+)", format_evaluation(evaluation))
    assert printed is not None and float(printed.group(1)) == pytest.approx(1 / s, rel=1e-3)


def test_real_tum_ground_truth_against_a_perturbed_copy_with_jittered_stamps(tmp_path):
    gt = read_tum(data_dir(TUM_DATA) / "groundtruth.txt")
    assert len(gt) == 8710 and gt.stamps_ns[0] == 1341847980790000000
    similarity = Similarity(Rotation.from_euler("zyx", [40, -10, 5], degrees=True).as_matrix(),
                            np.array([2.0, -1.0, 0.5]), 0.5)
    jitter = np.random.default_rng(1).integers(-500_000, 500_001, len(gt))  # the truth's stamps are >= 1.2 ms apart
    est = read_tum(write_tum(tmp_path / "est.txt", gt.stamps_ns + jitter, perturbed(gt.poses, 0.01, similarity)))
    check_sim3_figures(est, gt, 0.01, 0.5, max_dt_s=0.001)


def test_real_kitti_ground_truth_against_a_perturbed_copy(tmp_path):
    gt = read_kitti(data_dir(KITTI_DATA) / "poses.txt")
    assert len(gt) == 51 and np.allclose(gt.poses[0], np.eye(4), atol=1e-6)
    assert np.allclose(gt.poses[-1][:3, 3], [-0.98, -1.19, 59.84], atol=0.01)
    similarity = Similarity(Rotation.from_rotvec([0.1, 0.3, -0.2]).as_matrix(), np.array([5.0, 0.0, -3.0]), 3.0)
    est = read_kitti(write_kitti(tmp_path / "est.txt", perturbed(gt.poses, 0.05, similarity)))
    check_sim3_figures(est, gt, 0.05, 3.0)
