"""Passes of ``SlamSystem`` over frames with ground truth (the ``room`` scene by frame index, or a
sequence of ``tests/accuracy/slam_sequences.py``), for the relocalisation and map file tests.

Run as a module it is the second process of the map file tests: it loads a map file in
localisation-only mode, runs a pass over the first FRAMES frames of SEQUENCE (``room``, ``tum``
or ``kitti``) and writes what it found::

    PYTHONPATH=. python -m tests.slam_passes SEQUENCE MAP_FILE FRAMES OUT.npz

``OUT.npz`` holds ``states``, ``poses``, ``truth`` and ``keyframe_ids`` of the pass (``SlamPass``)
and ``revision_change``, how much the map's revision grew during the pass.
"""

from __future__ import annotations

import itertools
import sys
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from services.geometry.camera import CameraModel
from services.geometry.evaluation import Similarity, absolute_trajectory_error, apply_similarity
from services.geometry.rotation import rotation_angle
from services.slam.system import FrameResult, SlamSystem
from services.synthetic import make_scene
from tests.accuracy.slam_sequences import Frames, sequence

NANOSECONDS = 1_000_000_000


@dataclass(frozen=True)
class SlamPass:
    """F frames: ``states`` (F,) str, ``poses`` (F, 4, 4) ``T_world_camera`` of the map (NaN rows
    without a pose), ``truth`` (F, 4, 4) true ``T_world_camera`` (NaN rows where unknown),
    ``keyframe_ids`` (F,) int64 (-1 for a frame not made a keyframe)."""

    states: np.ndarray
    poses: np.ndarray
    truth: np.ndarray
    keyframe_ids: np.ndarray

    @property
    def posed(self) -> np.ndarray:
        """(F,) bool: frames with a pose and a true pose."""
        return np.all(np.isfinite(self.poses), axis=(1, 2)) & np.all(np.isfinite(self.truth), axis=(1, 2))

    def alignment(self) -> Similarity:
        """The Sim(3) (Umeyama on the camera centres) taking the map's world onto the truth's."""
        return absolute_trajectory_error(self.poses[self.posed], self.truth[self.posed], "sim3").alignment

    def ate_m(self) -> float:
        """RMS position error (m) of the posed frames after their own Sim(3) alignment."""
        return float(absolute_trajectory_error(self.poses[self.posed], self.truth[self.posed], "sim3").stats.rmse)

    def error_under_m(self, alignment: Similarity) -> float:
        """RMS position error (m) of the posed frames brought into the truth's world by ``alignment``."""
        aligned = apply_similarity(alignment, self.poses[self.posed])
        return float(np.sqrt(np.mean(np.sum((aligned[:, :3, 3] - self.truth[self.posed][:, :3, 3]) ** 2, axis=1))))


def room_scene():
    """The ``room`` scene of these tests (640x480, 30 fps, seed 0)."""
    return make_scene("room")


def room_frames(scene, indices: Iterable[int]) -> Frames:
    """``(stamp_ns, image, true T_world_cam0)`` of the scene's frames ``indices``."""
    for index in indices:
        frame = scene.render(index)
        yield int(round(frame.time_s * NANOSECONDS)), frame.images["cam0"], frame.truth["cam0"][0][2]


def feed(system: SlamSystem, scene, index: int, image: np.ndarray | None = None) -> FrameResult:
    """Frame ``index`` of ``scene`` through ``system`` (or ``image`` in its place, at its time)."""
    stamp_ns, own, _ = next(room_frames(scene, [index]))
    return system.process(stamp_ns, own if image is None else image)


def run_frames(system: SlamSystem, frames: Frames) -> SlamPass:
    """Every frame of ``frames`` through ``system``."""
    states, poses, truth, keyframe_ids = [], [], [], []
    for stamp_ns, image, T_true in frames:
        result = system.process(stamp_ns, image)
        states.append(result.state.value)
        poses.append(np.full((4, 4), np.nan) if result.T_world_camera is None else result.T_world_camera)
        truth.append(np.full((4, 4), np.nan) if T_true is None else T_true)
        keyframe_ids.append(-1 if result.keyframe_id is None else result.keyframe_id)
    return SlamPass(np.array(states), np.array(poses).reshape(-1, 4, 4), np.array(truth).reshape(-1, 4, 4),
                    np.array(keyframe_ids, np.int64))


def run_pass(system: SlamSystem, scene, indices: Iterable[int]) -> SlamPass:
    """The room scene's frames ``indices`` through ``system``."""
    return run_frames(system, room_frames(scene, indices))


def first_frames(name: str, count: int) -> tuple[CameraModel, Frames]:
    """The camera and the first ``count`` frames of sequence ``name`` (``slam_sequences.sequence``)."""
    frames = sequence(name)
    return frames.camera, itertools.islice(frames.frames, count)


def aligned_errors(T_world_camera: np.ndarray, T_true: np.ndarray, alignment: Similarity,
                   rotation_fix: np.ndarray) -> tuple[float, float]:
    """``(position error m, rotation error deg)`` of one (4, 4) pose of the map brought into the scene's
    world by ``alignment``, its orientation corrected by ``rotation_fix`` (3, 3) (``orientation_fix``)."""
    aligned = apply_similarity(alignment, T_world_camera[None])[0]
    error_m = float(np.linalg.norm(aligned[:3, 3] - T_true[:3, 3]))
    return error_m, float(np.degrees(rotation_angle(rotation_fix @ aligned[:3, :3], T_true[:3, :3])))


def orientation_fix(run: SlamPass, alignment: Similarity) -> np.ndarray:
    """(3, 3) the rotation best taking the aligned orientations of ``run``'s posed frames onto the
    truth's (chordal mean): the Sim(3) from camera centres alone leaves the rotation poorly fixed
    when the path is short."""
    aligned = apply_similarity(alignment, run.poses[run.posed])
    M = np.einsum("nij,nkj->ik", run.truth[run.posed][:, :3, :3], aligned[:, :3, :3])
    U, _, Vt = np.linalg.svd(M)
    return U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt


def main(argv: list[str]) -> int:
    name, map_path, count, out = argv[0], argv[1], int(argv[2]), argv[3]
    camera, frames = first_frames(name, count)
    system = SlamSystem(camera, mapping="inline", map_path=map_path, localisation_only=True)
    revision = system.map_revision
    run = run_frames(system, frames)
    system.close()
    np.savez(out, states=run.states, poses=run.poses, truth=run.truth, keyframe_ids=run.keyframe_ids,
             revision_change=system.map_revision - revision)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
