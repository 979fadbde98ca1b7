"""Sequences with ground truth for the monocular SLAM system, and one run of ``SlamSystem`` over one.

* ``room``: the synthetic ``room`` scene, 640x480 at 30 fps (``services.synthetic``).
* ``jittered@<seed>``: the same scene at uneven times, 150 frames whose gaps are drawn from an
  exponential distribution of mean 1/30 s (``seed`` seeds the draw), each frame stamped with its time.
* ``busy_stamped(sequence, seed)``: a sequence's frames restamped as a busy pipeline stamps them by the
  wall clock (its own gaps plus random waits and stalls).
* ``without(sequence, dropped)``: a sequence with some of its frames left out, as a pipeline that falls
  behind drops them; ``every(sequence, step)``: one frame in ``step`` kept, as a pipeline that keeps up
  with a third of the frames (``step`` 3) takes them.
* ``kitti``: KITTI odometry sequence 06, frames 0-50 (1226x370, 10 Hz, a car driving 60 m).
* ``tum``: TUM RGB-D fr3/long_office_household, 20 frames about 1 s apart (640x480, hand-held).
* ``loop``: the room's ``path="loop"``: once round the room in ``LOOP_S`` seconds and on for
  ``LOOP_OVERLAP`` of a turn over its start, at ``LOOP_FPS`` with image noise ``LOOP_NOISE`` grey levels
  (where a run without loop closing drifts by several centimetres).

The system runs as users run it, its local mapping in a process of its own (``mapping="process"``,
the default) unless told otherwise, fed the frames back to back as a lossless run feeds it: each new
keyframe is mapped before the next frame is tracked (``wait_for_mapping``), so the figures are those of
inline mapping (``mapping="inline"``) and do not depend on the load. Scoring: ATE RMSE after a Sim(3) alignment
(``services.geometry.evaluation``) of every frame given a pose, against the ground truth of the same
frame. ``python -m tests.accuracy.slam_sequences
[room|room@<seed>|jittered@<seed>|loop|kitti|tum ...][~<seed>][%<step>][-<first>:<end> ...]
[--mapping=process|thread|inline] [--frames=N] [--loop-closing=off]`` prints the figures (``-<first>:<end>``:
without frames first to end - 1; ``%<step>``: one frame in ``step``; ``--frames``: of each sequence's first N
frames only; ``--loop-closing=off`` without loop closing).
"""

from __future__ import annotations

import itertools
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from protocol.tracking_state import TrackingState
from services.geometry.camera import CameraModel
from services.geometry.evaluation import absolute_trajectory_error, associate
from services.recorder.trajectories import read_kitti, read_tum
from services.slam.system import SlamSettings, SlamSystem
from services.synthetic import Scene, make_scene
from tests.data import data_root

KITTI = "vo_kitti_odometry_seq06_frames000-050"
TUM = "tum_rgbd_fr3_long_office_household_1hz"
TUM_K = np.array([[535.4, 0.0, 320.1], [0.0, 539.2, 247.6], [0.0, 0.0, 1.0]])
ROOM_FRAMES = 600
JITTERED_FRAMES = 150
JITTERED_FPS = 3000.0
"""The jittered room is rendered from a scene of this frame rate, each frame the one nearest its time."""
MAX_GT_DT_NS = 20_000_000
"""A TUM image is scored against the ground-truth sample within 20 ms (the first image has none)."""
JITTER_MEAN_S, STALL_EVERY, STALL_MAX_S = 0.02, 10, 0.6
LOOP_S, LOOP_FPS, LOOP_NOISE, LOOP_OVERLAP = 20.0, 15.0, 6.0, 0.15
LOOP_FRAMES = round(LOOP_S * LOOP_FPS)
"""Frames of one turn of the loop: frame ``i + LOOP_FRAMES`` is where frame ``i`` was."""

Frames = Iterator[tuple[int, np.ndarray, np.ndarray | None]]
"""(stamp_ns, image, true T_world_camera or None)."""


@dataclass(frozen=True)
class Sequence:
    name: str
    camera: CameraModel
    frames: Frames


def room(seed: int = 0) -> Sequence:
    """``ROOM_FRAMES`` frames of the synthetic room of ``seed``, stamped by the scene's clock."""
    scene = make_scene("room", seed=seed)

    def frames() -> Frames:
        for index in range(ROOM_FRAMES):
            frame = scene.render(index)
            yield round(frame.time_s * 1e9), frame.images["cam0"], frame.truth["cam0"][0][2]

    return Sequence("room" if seed == 0 else f"room@{seed}", scene.cameras[0], frames())


def loop_scene() -> Scene:
    """The room on its loop path, as the ``loop`` sequence renders it."""
    return make_scene("room", path="loop", loop_s=LOOP_S, fps=LOOP_FPS, noise_std=LOOP_NOISE)


def room_loop() -> Sequence:
    """The room's loop path (module docstring), ``1 + LOOP_OVERLAP`` turns."""
    scene = loop_scene()

    def frames() -> Frames:
        for index in range(round((1 + LOOP_OVERLAP) * LOOP_FRAMES)):
            frame = scene.render(index)
            yield round(frame.time_s * 1e9), frame.images["cam0"], frame.truth["cam0"][0][2]

    return Sequence("loop", scene.cameras[0], frames())


def busy_stamped(sequence: Sequence, seed: int) -> Sequence:
    """``sequence`` stamped as a busy pipeline stamps frames by the wall clock: each gap between two
    stamps is the sequence's own plus an exponential wait (mean ``JITTER_MEAN_S``) and, in one gap of
    ``STALL_EVERY``, a stall of up to ``STALL_MAX_S`` (random, from ``seed``)."""
    rng = np.random.default_rng(seed)

    def frames() -> Frames:
        previous, stamp = None, 0
        for own, image, truth in sequence.frames:
            wait = rng.exponential(JITTER_MEAN_S) + (rng.random() < 1 / STALL_EVERY) * rng.uniform(0, STALL_MAX_S)
            stamp += (0 if previous is None else own - previous) + round(wait * 1e9)
            previous = own
            yield stamp, image, truth

    return Sequence(f"{sequence.name}~{seed}", sequence.camera, frames())


def without(sequence: Sequence, dropped: set[int]) -> Sequence:
    """``sequence`` without its frames of indices ``dropped`` (counted from 0)."""
    frames = (frame for index, frame in enumerate(sequence.frames) if index not in dropped)
    return Sequence(f"{sequence.name} without {len(dropped)} frames", sequence.camera, frames)


def every(sequence: Sequence, step: int) -> Sequence:
    """``sequence`` with one frame in ``step`` kept (the first, then every ``step``-th), at their own stamps."""
    return Sequence(f"{sequence.name}%{step}", sequence.camera, itertools.islice(sequence.frames, 0, None, step))


def jittered_room(seed: int) -> Sequence:
    """The room (seed 0) at the times of ``JITTERED_FRAMES`` exponential gaps of mean 1/30 s from 0
    (two times falling on one frame of ``JITTERED_FPS`` give one frame)."""
    scene = make_scene("room", fps=JITTERED_FPS)
    gaps = np.random.default_rng(seed).exponential(1.0 / 30.0, JITTERED_FRAMES - 1)
    indices = np.unique(np.round(np.concatenate([[0.0], np.cumsum(gaps)]) * JITTERED_FPS).astype(np.int64))

    def frames() -> Frames:
        for index in indices.tolist():
            frame = scene.render(index)
            yield round(frame.time_s * 1e9), frame.images["cam0"], frame.truth["cam0"][0][2]

    return Sequence(f"jittered@{seed}", scene.cameras[0], frames())


def kitti(folder: Path) -> Sequence:
    P0 = np.array((folder / "calib.txt").read_text().splitlines()[0].split()[-12:], float).reshape(3, 4)
    truth = read_kitti(folder / "poses.txt").poses
    files = sorted((folder / "image_0").glob("*.png"))
    first = cv2.imread(str(files[0]), cv2.IMREAD_UNCHANGED)
    camera = CameraModel("cam0", first.shape[1], first.shape[0], P0[:, :3], np.zeros(5), np.eye(4))

    def frames() -> Frames:
        for index, path in enumerate(files):
            yield index * 100_000_000, cv2.imread(str(path), cv2.IMREAD_UNCHANGED), truth[index]

    return Sequence("kitti", camera, frames())


def tum(folder: Path) -> Sequence:
    truth = read_tum(folder / "groundtruth.txt")
    assert truth.stamps_ns is not None
    files = sorted((folder / "rgb").glob("*.png"))
    stamps = np.array([round(float(path.stem) * 1e9) for path in files], np.int64)
    pairs = dict(associate(stamps, truth.stamps_ns, MAX_GT_DT_NS).tolist())
    camera = CameraModel("rgb", 640, 480, TUM_K, np.zeros(5), np.eye(4))

    def frames() -> Frames:
        for index, path in enumerate(files):
            gt = truth.poses[pairs[index]] if index in pairs else None
            yield int(stamps[index]), cv2.imread(str(path), cv2.IMREAD_UNCHANGED), gt

    return Sequence("tum", camera, frames())


@dataclass(frozen=True)
class SlamRun:
    """A run's figures: ``ate_m`` (Sim(3)-aligned RMSE over the ``scored`` frames), ``length_m`` of
    the true path over those frames, per-frame ``states``, ``first_tracked`` frame index,
    ``tracking_ms`` (N,) per frame without the inline mapping and the waits for the mapper,
    ``stage_ms`` median per stage over the tracked frames, ``mapping_ms`` median wall time per keyframe
    mapped, ``keyframes`` and ``points`` at the end; ``keyframe_ate_m`` the ATE of the keyframes' final
    (bundle adjusted) poses; ``final_ate_m`` that of the final trajectory (``SlamSystem.trajectory``:
    every tracked frame through its reference keyframe's final pose), the online poses' being ``ate_m``;
    ``maps_given_up``: young maps lost and started again (``SlamSystem.maps_given_up``)."""

    name: str
    ate_m: float
    final_ate_m: float
    keyframe_ate_m: float
    length_m: float
    scored: int
    states: list[TrackingState]
    first_tracked: int
    tracking_ms: np.ndarray
    stage_ms: dict[str, float]
    mapping_ms: float
    keyframes: int
    points: int
    maps_given_up: int = 0

    @property
    def lost(self) -> int:
        return sum(state is TrackingState.LOST for state in self.states)

    @property
    def untracked_after_start(self) -> int:
        return sum(state is not TrackingState.TRACKING for state in self.states[self.first_tracked:])

    def line(self) -> str:
        stages = ", ".join(f"{k} {v:.1f}" for k, v in self.stage_ms.items())
        final, online = (100 * ate / self.length_m for ate in (self.final_ate_m, self.ate_m))
        return (f"{self.name}: ATE final {self.final_ate_m:.4f} m ({final:.2f} % of {self.length_m:.2f} m), "
                f"online {self.ate_m:.4f} m ({online:.2f} %) over {self.scored} frames "
                f"(keyframes: {self.keyframe_ate_m:.4f} m); "
                f"first tracked frame {self.first_tracked}, lost {self.lost}, "
                f"untracked after start {self.untracked_after_start}; tracking {1000 / np.mean(self.tracking_ms):.1f} "
                f"frames/s (median ms: {stages}); mapping {self.mapping_ms:.0f} ms per keyframe; "
                f"{self.keyframes} keyframes, {self.points} points"
                + (f"; {self.maps_given_up} maps given up" if self.maps_given_up else ""))


def run(sequence: Sequence, mapping: str = "process", settings: SlamSettings | None = None) -> SlamRun:
    """``SlamSystem`` (``settings``, default ones unless given; ``mapping`` in its process unless told,
    keyframe decisions waiting for the mapper) over every frame of ``sequence``, back to back."""
    system = SlamSystem(sequence.camera, settings, mapping=mapping, wait_for_mapping=True)
    estimated, true, states, tracking = [], [], [], []
    truth_at: dict[int, np.ndarray] = {}
    stages: dict[str, list[float]] = {}
    try:
        for stamp_ns, image, gt in sequence.frames:
            result = system.process(stamp_ns, image)
            states.append(result.state)
            timings = result.timings_ms
            tracking.append(timings["total"] - timings.get("mapping", 0.0) - timings.get("mapping_wait", 0.0))
            if result.state is TrackingState.TRACKING:
                for stage in ("keypoints", "match", "pose", "local_map", "keyframe"):
                    stages.setdefault(stage, []).append(timings.get(stage, 0.0) - (
                        timings.get("mapping", 0.0) + timings.get("mapping_wait", 0.0) if stage == "keyframe" else 0.0))
            if gt is not None:
                truth_at[stamp_ns] = gt
            if result.T_world_camera is not None and gt is not None:
                estimated.append(result.T_world_camera)
                true.append(gt)
        _, points = system.map_points()
        keyframes = [(stamp, T) for _, stamp, T in system.keyframe_poses() if stamp in truth_at]
        final = [(stamp, T) for stamp, T in system.trajectory() if stamp in truth_at]
    finally:
        system.close()
    mapped = [record.wall_ms for record in system._mapper.history]
    true_poses = np.array(true)
    ate = absolute_trajectory_error(np.array(estimated), true_poses, "sim3")
    length = float(np.sum(np.linalg.norm(np.diff(true_poses[:, :3, 3], axis=0), axis=1)))
    first = next((i for i, state in enumerate(states) if state is TrackingState.TRACKING), len(states))
    keyframe_ate, final_ate = (absolute_trajectory_error(np.array([T for _, T in poses]),
                                                         np.array([truth_at[stamp] for stamp, _ in poses]), "sim3")
                               for poses in (keyframes, final))
    assert len(final) == len(estimated), f"{sequence.name}: {len(final)} frames in the trajectory, {len(estimated)}"
    return SlamRun(sequence.name, ate.stats.rmse, final_ate.stats.rmse, keyframe_ate.stats.rmse, length,
                   len(estimated), states, first,
                   np.array(tracking), {k: float(np.median(v)) for k, v in stages.items()},
                   float(np.median(mapped)) if mapped else 0.0, len(keyframes), len(points), system.maps_given_up)


def sequence(name: str) -> Sequence:
    """``room`` (``room@<seed>`` for another seed of the scene: its textures and path), ``jittered@<seed>``,
    ``loop``, ``kitti`` or ``tum``; any of them ``~<seed>`` restamped by ``busy_stamped`` with that seed,
    ``%<step>`` one frame in ``step`` (``every``), and
    ``-<first>:<end>`` (repeated) without those frames."""
    base, *spans = name.split("-")
    if spans:
        dropped = {i for span in spans for i in range(*map(int, span.split(":")))}
        return without(sequence(base), dropped)
    if "~" in name:
        base, _, seed = name.partition("~")
        return busy_stamped(sequence(base), int(seed))
    if "%" in name:
        base, _, step = name.partition("%")
        return every(sequence(base), int(step))
    if name.startswith("room"):
        return room(int(name.partition("@")[2] or 0))
    if name == "loop":
        return room_loop()
    if name.startswith("jittered@"):
        return jittered_room(int(name.partition("@")[2]))
    return kitti(data_root() / KITTI) if name == "kitti" else tum(data_root() / TUM)


def first(chosen: Sequence, count: int | None) -> Sequence:
    """``chosen`` cut to its first ``count`` frames (all of them when None)."""
    return Sequence(chosen.name, chosen.camera, itertools.islice(chosen.frames, count))


if __name__ == "__main__":
    options = dict(a[2:].partition("=")[::2] for a in sys.argv[1:] if a.startswith("--"))
    names = [a for a in sys.argv[1:] if not a.startswith("--")]
    count = int(options["frames"]) if "frames" in options else None
    chosen = SlamSettings(loop_closing=options.get("loop-closing", "on") != "off")
    for name in names or ["room", "kitti", "tum"]:
        print(run(first(sequence(name), count), options.get("mapping", "process"), chosen).line(), flush=True)
