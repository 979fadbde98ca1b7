"""A map saved after a pass over the room scene, loaded by another process, localises a second pass
over the same frames as well as the first pass tracked them.

The first pass maps frames 0-149 (inline mapping) and saves the map when its system closes. A new
Python process (``tests/slam_room_pass.py``) loads the file in localisation-only mode and runs the
same frames: it must relocalise on its first frame, track every frame after, change nothing in the
map, and its poses, brought into the scene's world by the Sim(3) of the first pass (same map, same
world), must be within ``MARGIN_M`` of the first pass's ATE. Loaded without ``localisation_only``, the map
grows again on the frames after.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from services.geometry.evaluation import absolute_trajectory_error, apply_similarity
from services.slam.map_file import read_header
from services.slam.system import SlamSystem
from tests.slam_room_pass import RoomPass, room_scene, run_pass

FRAMES = 150
MARGIN_M = 0.005
ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def first_pass(tmp_path_factory) -> tuple[RoomPass, Path, int]:
    """The first pass, the map file its system saved on closing, and its keyframe count."""
    scene = room_scene()
    map_path = tmp_path_factory.mktemp("map") / "room.map.npz"
    system = SlamSystem(scene.cameras[0], mapping_thread=False, save_path=map_path)
    first = run_pass(system, scene, range(FRAMES))
    keyframes = len(system.keyframe_poses())
    system.close()
    return first, map_path, keyframes


def test_a_saved_map_localises_the_same_frames_in_a_new_process(first_pass, tmp_path):
    first, map_path, keyframes = first_pass
    header = read_header(map_path)
    assert header["counts"]["keyframes"] == keyframes
    out = tmp_path / "second.npz"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    start = time.perf_counter()
    subprocess.run([sys.executable, "-m", "tests.slam_room_pass", str(map_path), str(FRAMES), str(out)], env=env,
                   cwd=ROOT, check=True, timeout=600)
    seconds = time.perf_counter() - start
    with np.load(out) as second:
        states, poses, keyframe_ids = second["states"], second["poses"], second["keyframe_ids"]
        revision_change = int(second["revision_change"])
    assert states[0] == "tracking", "relocalised on its first frame"
    assert np.all(states == "tracking") and np.all(np.isfinite(poses))
    assert np.all(keyframe_ids < 0) and revision_change == 0, "localisation-only changes nothing in the map"
    alignment = first.alignment()
    truth = first.truth
    second_m = float(np.sqrt(np.mean(np.sum((apply_similarity(alignment, poses)[:, :3, 3] - truth[:, :3, 3]) ** 2,
                                            axis=1))))
    own_m = float(absolute_trajectory_error(poses, truth, "sim3").stats.rmse)
    first_m = first.ate_m()
    size_kb = map_path.stat().st_size / 1024
    print(f"first pass: ATE {first_m * 100:.2f} cm over {int(first.posed.sum())} frames, {keyframes} keyframes, "
          f"{header['counts']['points']} points, map file {size_kb:.0f} kB; second pass in a new process "
          f"({seconds:.0f} s): {FRAMES} frames tracked, ATE {second_m * 100:.2f} cm under the first pass's "
          f"alignment, {own_m * 100:.2f} cm under its own")
    assert second_m <= first_m + MARGIN_M


def test_a_loaded_map_grows_when_mapping(first_pass):
    first, map_path, keyframes = first_pass
    scene = room_scene()
    system = SlamSystem(scene.cameras[0], mapping_thread=False, map_path=map_path)
    later = run_pass(system, scene, range(FRAMES, FRAMES + 60))
    system.close()
    assert np.all(later.states == "tracking")
    made = later.keyframe_ids[later.keyframe_ids >= 0]
    assert len(made) > 0 and made.min() >= keyframes and len(system.keyframe_poses()) == keyframes + len(made)
    alignment = first.alignment()
    errors = np.linalg.norm(apply_similarity(alignment, later.poses)[:, :3, 3] - later.truth[:, :3, 3], axis=1)
    print(f"frames {FRAMES}-{FRAMES + 59} on the loaded map, mapping: {len(made)} keyframes made, position error "
          f"under the first pass's alignment {100 * np.sqrt(np.mean(errors ** 2)):.2f} cm RMS")
    assert np.sqrt(np.mean(errors ** 2)) <= 3 * first.ate_m()
