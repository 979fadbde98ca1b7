"""``artrack eval`` as a process on trajectory files written for the test (no bus): printed figures against
hand-computed ones, user errors as one line and exit 2, and the same figures as evo's commands."""

from __future__ import annotations

import json
import math
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from protocol import FrameTransform, GroundTruth, Header, Pose, encode
from protocol.spatial import Transform
from services.geometry.rotation import matrix_from_rotvec
from services.geometry.se3 import make_transform
from services.recorder.trajectories import read_kitti
from services.recorder.writing import RecordingWriter
from tests.data import data_dir

pytestmark = pytest.mark.integration

T0_NS = 1_700_000_000_000_000_000
STEP_NS = 100_000_000


def artrack(*args: str | Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "services.cli", *map(str, args)], capture_output=True, text=True,
                          timeout=120)


def figures(text: str) -> dict[str, float]:
    """``{"ATE rmse": ..., "trans median": ..., "scale": ...}`` from the printed text."""
    found = {}
    for label, rest in re.findall(r"^\s*(ATE|trans|rot) \((?:m|deg)\)\s+(.*)$", text, re.M):
        found.update({f"{label} {name}": float(value) for name, value in re.findall(r"(\w+) (\S+)", rest)})
    scale = re.search(r"scale (\S+)", text)
    if scale:
        found["scale"] = float(scale.group(1))
    return found


def walk(steps: int, step_m: float, yaw_per_step: float = 0.0) -> np.ndarray:
    """(steps + 1, 4, 4) poses walking along their own x axis, turning about z after each step."""
    poses = [np.eye(4)]
    for _ in range(steps):
        poses.append(poses[-1] @ make_transform(matrix_from_rotvec([0.0, 0.0, yaw_per_step]), [step_m, 0.0, 0.0]))
    return np.array(poses)


def write_tum(path: Path, poses: np.ndarray, stamps_ns: np.ndarray | None = None) -> Path:
    stamps_ns = T0_NS + STEP_NS * np.arange(len(poses)) if stamps_ns is None else stamps_ns
    path.write_text("# timestamp tx ty tz qx qy qz qw\n" + "".join(
        f"{s // 10**9}.{s % 10**9:09d} " + " ".join(repr(float(v)) for v in
                                                    [*T[:3, 3], *Rotation.from_matrix(T[:3, :3]).as_quat()]) + "\n"
        for s, T in zip(stamps_ns, poses, strict=True)))
    return path


def write_kitti(path: Path, poses: np.ndarray) -> Path:
    path.write_text("".join(" ".join(repr(float(v)) for v in T[:3].ravel()) + "\n" for T in poses))
    return path


def one_error_line(done: subprocess.CompletedProcess) -> str:
    lines = [line for line in done.stderr.splitlines() if line.strip()]
    assert done.returncode == 2 and len(lines) == 1 and not done.stdout, (done.returncode, done.stdout, done.stderr)
    return lines[0]


def test_a_known_offset_gives_its_ate_and_a_stretch_its_rpe(tmp_path):
    gt = walk(20, 1.0, math.radians(5))
    est = walk(20, 1.1, math.radians(5))
    est[:, :3, 3] += [0.3, 0.4, 0.0]  # a world offset: ATE sees it unaligned, RPE never
    gt_file, est_file = write_tum(tmp_path / "gt.txt", gt), write_tum(tmp_path / "est.txt", est)
    done = artrack("eval", est_file, gt_file, "--align", "none")
    assert done.returncode == 0, done.stderr
    printed = figures(done.stdout)
    assert "matched      21 poses (21 estimated, 21 true) by stamp" in done.stdout
    offsets = np.linalg.norm(est[:, :3, 3] - gt[:, :3, 3], axis=1)
    assert printed["ATE rmse"] == pytest.approx(math.sqrt(np.mean(offsets**2)), abs=1e-6)
    assert printed["ATE max"] == pytest.approx(offsets.max(), abs=1e-6)
    assert printed["trans rmse"] == pytest.approx(0.1, abs=1e-6) and printed["trans max"] == pytest.approx(0.1)
    assert printed["rot max"] == pytest.approx(0.0, abs=1e-4)

    shifted = est.copy()
    shifted[:, :3, 3] = gt[:, :3, 3] + [0.3, 0.4, 0.0]
    done = artrack("eval", write_tum(tmp_path / "shifted.txt", shifted), gt_file, "--align", "none", "--delta", "2")
    assert figures(done.stdout)["ATE median"] == pytest.approx(0.5, abs=1e-6)
    assert "RPE over 2 frames: 19 pairs" in done.stdout
    done = artrack("eval", tmp_path / "shifted.txt", gt_file)  # se3 by default: the offset is aligned away
    assert figures(done.stdout)["ATE max"] == pytest.approx(0.0, abs=1e-6)


def test_sim3_json_kitti_by_index_and_a_distance_delta(tmp_path):
    gt = walk(30, 0.5, math.radians(3))
    R = Rotation.from_rotvec([0.2, -0.1, 0.4]).as_matrix()
    est = gt.copy()
    est[:, :3, :3] = R @ gt[:, :3, :3]
    est[:, :3, 3] = 0.25 * gt[:, :3, 3] @ R.T + [1.0, 2.0, 3.0]
    stamps = T0_NS + 33_000_000 * np.arange(len(gt))  # a stamped estimate against an unstamped truth: by index
    done = artrack("eval", write_tum(tmp_path / "est.txt", est, stamps), write_kitti(tmp_path / "gt.txt", gt),
                   "--align", "sim3", "--delta", "2", "--delta-unit", "m", "--json")
    assert done.returncode == 0, done.stderr
    result = json.loads(done.stdout)
    assert result["matched_by"] == "index" and result["matched"] == 31 and result["scale"] == pytest.approx(4.0)
    assert result["matched_note"] == (f"{tmp_path / 'est.txt'} has stamps but no frame numbers, {tmp_path / 'gt.txt'} "
                                      "frame numbers but no stamps: row i of each taken as the same instant")
    assert np.allclose(result["alignment"]["R"], R.T, atol=1e-9) and result["ate_m"]["max"] < 1e-9
    assert result["rpe"]["pairs"] == 27 and result["rpe"]["translation_m"]["max"] < 1e-9  # 4 steps of 0.5 m
    text = artrack("eval", tmp_path / "est.txt", tmp_path / "gt.txt", "--align", "se3")
    assert figures(text.stdout)["ATE rmse"] > 1.0  # without the scale no rigid motion fits


def test_a_recording_key_against_its_ground_truth(tmp_path):
    path = tmp_path / "session.mcap"
    writer = RecordingWriter(path, metadata={"namespace": "ar", "rig": "lab"})
    for i in range(20):
        true = Transform(translation=(0.1 * i, 0.0, 1.0), rotation=(0.0, 0.0, math.sin(i / 40), math.cos(i / 40)))
        header = Header(stamp_ns=T0_NS + i * 33_333_333, frame_id="world", seq=i)
        est = true.model_copy(update={"translation": (0.1 * i + 0.01, 0.0, 1.0)})
        writer.write("ar/lab/pose/wand", encode(Pose(header=header, child_frame_id="body/wand", transform=est)), i)
        writer.write("ar/lab/cam0/truth", encode(GroundTruth(header=header, transforms=(
            FrameTransform(parent_frame="world", child_frame="body/wand", transform=true),))), i)
    writer.close()
    done = artrack("eval", path, path, "--est-key", "pose/wand", "--gt-key", "cam0/truth", "--child", "body/wand",
                   "--align", "none")
    assert done.returncode == 0, done.stderr
    assert "matched      20 poses" in done.stdout and figures(done.stdout)["ATE rmse"] == pytest.approx(0.01)
    assert "choose a child frame with --child" in one_error_line(
        artrack("eval", path, path, "--est-key", "pose/wand", "--gt-key", "cam0/truth"))


def test_the_truth_may_name_its_child_frame_otherwise_than_the_estimate(tmp_path):
    path = tmp_path / "session.mcap"
    writer = RecordingWriter(path, metadata={"namespace": "ar", "rig": "lab"})
    for i in range(10):
        true = Transform(translation=(0.0, 0.01 * i, 0.5))
        header = Header(stamp_ns=T0_NS + i * 33_333_333, frame_id="cam0", seq=i)
        est = true.model_copy(update={"translation": (0.002, 0.01 * i, 0.5)})
        writer.write("ar/lab/pose/cam0/target/poster",
                     encode(Pose(header=header, child_frame_id="target/poster", transform=est)), i)
        writer.write("ar/lab/cam0/truth", encode(GroundTruth(header=header, transforms=(
            FrameTransform(parent_frame="cam0", child_frame="target", transform=true),))), i)
    writer.close()
    keys = ("--est-key", "pose/cam0/target/poster", "--gt-key", "cam0/truth", "--align", "none")
    done = artrack("eval", path, path, *keys, "--gt-child", "target")
    assert done.returncode == 0, done.stderr
    assert "matched      10 poses" in done.stdout and figures(done.stdout)["ATE rmse"] == pytest.approx(0.002)
    assert artrack("eval", path, path, *keys, "--child", "target").returncode == 2  # the estimate has no `target`


def test_user_errors_are_one_line_and_exit_2(tmp_path):
    gt = write_tum(tmp_path / "gt.txt", walk(5, 1.0))
    assert f"cannot read {tmp_path / 'nowhere.txt'}: No such file or directory" in one_error_line(
        artrack("eval", tmp_path / "nowhere.txt", gt))
    bad = tmp_path / "bad.txt"
    bad.write_text(gt.read_text() + "1700000001.0 1 2 3 0 0 0\n")
    assert f"{bad}:8: a TUM file (stamp tx ty tz qx qy qz qw) needs 8 numbers a line, found 7" in one_error_line(
        artrack("eval", bad, gt))
    late = write_tum(tmp_path / "late.txt", walk(5, 1.0), T0_NS + 10**10 + STEP_NS * np.arange(6))
    assert f"{late} (6 poses) and {gt} (6 poses) hardly overlap: 0 paired by stamp within 0.02 s, at least 3 " \
           "needed" in one_error_line(artrack("eval", late, gt))
    assert "whole number >= 1" in one_error_line(artrack("eval", gt, gt, "--delta", "0.5"))


def write_slam_run(path: Path, poses: np.ndarray, first_frame: int) -> Path:
    """A recording of ``pose/slam/cam0``: ``poses`` (N, 4, 4) ``T_map_cam0`` tracked from frame ``first_frame`` on,
    stamped by the wall clock as a run on an image folder is."""
    writer = RecordingWriter(path, metadata={"namespace": "ar", "rig": "rig0"})
    for i, T in enumerate(poses):
        header = Header(stamp_ns=T0_NS + STEP_NS * i, frame_id="map", seq=first_frame + i)
        transform = Transform(translation=tuple(T[:3, 3]), rotation=tuple(Rotation.from_matrix(T[:3, :3]).as_quat()))
        pose = Pose(header=header, child_frame_id="cam0", transform=transform)
        writer.write("ar/rig0/pose/slam/cam0", encode(pose), i)
    writer.close()
    return path


def test_a_run_that_starts_at_frame_2_scores_against_the_real_kitti_truth_by_frame_number(tmp_path):
    truth = data_dir("vo_kitti_odometry_seq06_frames000-050") / "poses.txt"
    true_poses = read_kitti(truth).poses
    run = write_slam_run(tmp_path / "run.mcap", true_poses[2:], first_frame=2)
    done = artrack("eval", run, truth, "--est-key", "pose/slam/cam0", "--align", "none")
    assert done.returncode == 0, done.stderr
    assert "matched      49 poses (49 estimated, 51 true) by frame number" in done.stdout
    assert figures(done.stdout)["ATE max"] == pytest.approx(0.0, abs=1e-6)
    by_index = artrack("eval", run, truth, "--est-key", "pose/slam/cam0", "--align", "none", "--match-by", "index")
    assert "by index" in by_index.stdout and figures(by_index.stdout)["ATE rmse"] > 2.0  # frame k + 2 against k

    exported = write_tum(tmp_path / "run.tum", true_poses[2:])  # what `artrack export` writes: no frame numbers
    refused = one_error_line(artrack("eval", exported, truth, "--align", "none"))
    assert f"nothing to pair {exported} (49 poses) and {truth} (51 poses) by: {exported} has stamps but no frame " \
           "numbers" in refused and "their counts differ" in refused
    kitti = tmp_path / "kitti"
    kitti.mkdir()
    shutil.copy(truth, kitti / "poses.txt")
    (kitti / "times.txt").write_text("".join(f"{i * STEP_NS / 1e9:.6e}\n" for i in range(51)))
    stamped = write_tum(tmp_path / "stamped.tum", true_poses[2:], STEP_NS * np.arange(2, 51) + 3_000_000)
    done = artrack("eval", stamped, kitti / "poses.txt", "--align", "none")
    assert done.returncode == 0, done.stderr
    assert "matched      49 poses (49 estimated, 51 true) by stamp within 0.02 s" in done.stdout
    assert figures(done.stdout)["ATE max"] == pytest.approx(0.0, abs=1e-6)


def test_two_unrelated_trajectories_are_refused_with_their_counts(tmp_path):
    truth = data_dir("vo_kitti_odometry_seq06_frames000-050") / "poses.txt"
    other = write_slam_run(tmp_path / "other.mcap", walk(231, 0.05, 0.02), first_frame=0)  # another run, 232 frames
    line = one_error_line(artrack("eval", other, truth, "--est-key", "pose/slam/cam0", "--align", "sim3"))
    assert line.endswith(f"{other} pose/slam/cam0 (232 poses) and {truth} (51 poses) hardly overlap: 51 paired by "
                         "frame number, at least 116 needed (half the estimate's poses, and no fewer than 3)"), line
    unstamped = write_tum(tmp_path / "other.tum", walk(231, 0.05, 0.02))
    assert "their counts differ" in one_error_line(artrack("eval", unstamped, truth))
    assert "51 paired by index, at least 116 needed" in one_error_line(
        artrack("eval", unstamped, truth, "--match-by", "index"))


def test_plot_draws_both_views(tmp_path):
    gt = write_tum(tmp_path / "gt.txt", walk(10, 0.2, 0.3))
    out = tmp_path / "eval.png"
    done = artrack("eval", gt, gt, "--plot", out)
    assert done.returncode == 0, done.stderr
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and out.stat().st_size > 10_000


def evo_command(name: str) -> str:
    """Path of evo's command ``name`` (on PATH or beside this Python); skips the test when absent."""
    found = shutil.which(name) or shutil.which(name, path=os.path.dirname(sys.executable))
    if found is None:
        pytest.skip(f"{name} not found on PATH: install evo (pip install 'artrack[evo]') to cross-check against it")
    return found


def evo_figures(*args: str | Path) -> dict[str, float]:
    done = subprocess.run([*map(str, args), "--no_warnings"], capture_output=True, text=True, timeout=300,
                          env={**os.environ, "MPLBACKEND": "Agg"})
    assert done.returncode == 0, done.stdout + done.stderr
    return {name: float(value) for name, value in re.findall(r"^\s*(rmse|mean|median|max)\s+(\S+)$", done.stdout,
                                                             re.M)}


def test_figures_agree_with_evo(tmp_path):
    ape, rpe = evo_command("evo_ape"), evo_command("evo_rpe")
    rng = np.random.default_rng(3)
    gt = walk(300, 0.05, 0.05)
    gt[:, :3, 3] += np.cumsum(rng.normal(0, 0.01, (len(gt), 3)), axis=0)
    R = Rotation.from_rotvec([0.3, 0.2, -0.5]).as_matrix()
    est = gt @ np.array([make_transform(matrix_from_rotvec(rng.normal(0, 0.01, 3)), np.zeros(3)) for _ in gt])
    est[:, :3, :3] = R @ est[:, :3, :3]
    est[:, :3, 3] = 0.7 * (gt[:, :3, 3] + rng.normal(0, 0.02, (len(gt), 3))) @ R.T + [1.0, -2.0, 0.5]
    stamps = T0_NS + STEP_NS * np.arange(len(gt))
    gt_file = write_tum(tmp_path / "gt.txt", gt, stamps)
    est_file = write_tum(tmp_path / "est.txt", est, stamps + rng.integers(-5_000_000, 5_000_000, len(gt)))
    for align, flag in (("sim3", "-as"), ("se3", "-a")):
        ours = json.loads(artrack("eval", est_file, gt_file, "--align", align, "--delta", "5", "--json").stdout)
        theirs = evo_figures(ape, "tum", gt_file, est_file, flag, "--t_max_diff", "0.02")
        assert theirs == pytest.approx({k: ours["ate_m"][k] for k in theirs}, abs=2e-6), (align, theirs, ours)
        common = ("tum", gt_file, est_file, flag, "--t_max_diff", "0.02", "--delta", "5", "--delta_unit", "f",
                  "--all_pairs")
        theirs = evo_figures(rpe, *common)
        assert theirs == pytest.approx({k: ours["rpe"]["translation_m"][k] for k in theirs}, abs=2e-6), align
        theirs = evo_figures(rpe, *common, "-r", "angle_deg")
        assert theirs == pytest.approx({k: ours["rpe"]["rotation_deg"][k] for k in theirs}, abs=2e-6), align


def test_a_damaged_recording_is_scored_up_to_the_damage_said_once_exit_3(tmp_path):
    whole = Path(__file__).resolve().parents[2] / "recordings" / "markers.mcap"  # 150 frames of truth
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(whole.read_bytes()[: whole.stat().st_size * 6 // 10])
    keys = ("--est-key", "cam0/truth", "--gt-key", "cam0/truth", "--child", "marker/0")
    done = artrack("eval", cut, cut, *keys)
    assert done.returncode == 3, done.stderr
    warnings = [line for line in done.stderr.splitlines() if "damaged" in line]
    assert len(warnings) == 1 and f"{cut} is damaged: stopped at byte" in warnings[0], done.stderr
    matched = int(re.search(r"matched\s+(\d+) poses", done.stdout).group(1))
    assert 3 <= matched < 150, done.stdout
    assert artrack("eval", whole, whole, *keys).returncode == 0
