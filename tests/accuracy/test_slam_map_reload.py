"""A map saved after a pass over a sequence, loaded by another process, localises a second pass over
the same frames as well as the first pass tracked them.

The first pass maps the frames (inline mapping) and saves the map when its system closes. A new
Python process (``python -m tests.slam_passes``) loads the file in localisation-only mode and runs the
same frames: it must relocalise on its first frame, track every frame after, change nothing in the
map, and its poses, brought into the truth's world by the Sim(3) of the first pass (same map, same
world), must be within ``MARGIN_M`` of the first pass's ATE. Sequences: the synthetic room (frames
0-149), TUM fr3 long_office_household at 1 Hz (20 frames) and KITTI 06 (frames 0-50). Loaded without
``localisation_only``, the room's map grows again on the frames after. Maps saved while the mapping
thread works load whole.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from services.slam.map.file import load_map, read_header
from services.slam.system import SlamSystem
from tests.accuracy.slam_sequences import KITTI, TUM
from tests.data import data_dir
from tests.slam_passes import SlamPass, first_frames, room_scene, run_frames, run_pass

pytestmark = [pytest.mark.integration, pytest.mark.slow]

SEQUENCES = {"room": (150, None), "tum": (20, TUM), "kitti": (51, KITTI)}
"""Name -> (frames, data set or None for the synthetic scene)."""
MARGIN_M = 0.005
ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def first_passes(tmp_path_factory):
    """Name -> (first pass, the map file its system saved on closing, its keyframe count), made on demand."""
    made: dict[str, tuple[SlamPass, Path, int]] = {}

    def first_pass(name: str) -> tuple[SlamPass, Path, int]:
        if name not in made:
            count, data = SEQUENCES[name]
            if data is not None:
                data_dir(data)
            camera, frames = first_frames(name, count)
            map_path = tmp_path_factory.mktemp(name) / f"{name}.map.npz"
            system = SlamSystem(camera, mapping="inline", save_path=map_path)
            run = run_frames(system, frames)
            keyframes = len(system.keyframe_poses())
            system.close()
            made[name] = (run, map_path, keyframes)
        return made[name]

    return first_pass


@pytest.mark.parametrize("name", list(SEQUENCES))
def test_a_saved_map_localises_the_same_frames_in_a_new_process(name, first_passes, tmp_path):
    first, map_path, keyframes = first_passes(name)
    header = read_header(map_path)
    assert header["counts"]["keyframes"] == keyframes
    out = tmp_path / "second.npz"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    count = SEQUENCES[name][0]
    start = time.perf_counter()
    subprocess.run([sys.executable, "-m", "tests.slam_passes", name, str(map_path), str(count), str(out)], env=env,
                   cwd=ROOT, check=True, timeout=600)
    seconds = time.perf_counter() - start
    with np.load(out) as second:
        run = SlamPass(second["states"], second["poses"], second["truth"], second["keyframe_ids"])
        revision_change = int(second["revision_change"])
    assert run.states[0] == "tracking", "relocalised on its first frame"
    assert np.all(run.states == "tracking") and np.all(np.isfinite(run.poses))
    assert np.all(run.keyframe_ids < 0) and revision_change == 0, "localisation-only changes nothing in the map"
    second_m, first_m = run.error_under_m(first.alignment()), first.ate_m()
    size_kb = map_path.stat().st_size / 1024
    print(f"{name}: first pass ATE {first_m * 100:.2f} cm over {int(first.posed.sum())} frames, {keyframes} "
          f"keyframes, {header['counts']['points']} points, map file {size_kb:.0f} kB; second pass in a new "
          f"process ({seconds:.0f} s): {count} frames tracked, ATE {second_m * 100:.2f} cm under the first pass's "
          f"alignment, {run.ate_m() * 100:.2f} cm under its own")
    assert second_m <= first_m + MARGIN_M


def test_a_loaded_map_grows_when_mapping(first_passes):
    first, map_path, keyframes = first_passes("room")
    count = SEQUENCES["room"][0]
    scene = room_scene()
    system = SlamSystem(scene.cameras[0], mapping="inline", map_path=map_path)
    later = run_pass(system, scene, range(count, count + 60))
    system.close()
    assert np.all(later.states == "tracking")
    made = later.keyframe_ids[later.keyframe_ids >= 0]
    assert len(made) > 0 and made.min() >= keyframes and len(system.keyframe_poses()) == keyframes + len(made)
    error_m = later.error_under_m(first.alignment())
    print(f"frames {count}-{count + 59} on the loaded map, mapping: {len(made)} keyframes made, position error "
          f"under the first pass's alignment {100 * error_m:.2f} cm RMS")
    assert error_m <= 3 * first.ate_m()


def test_maps_saved_while_the_mapping_thread_works_load_whole(tmp_path):
    scene = room_scene()
    system = SlamSystem(scene.cameras[0], mapping="thread")
    saved = []
    try:
        for index in range(90):
            run_pass(system, scene, [index])
            if index % 10 == 9:
                path = tmp_path / f"at{index}.npz"
                system.save_map(path)
                saved.append(path)
    finally:
        system.close()
    sizes = []
    for path in saved:
        header = read_header(path)
        counts = header["counts"]
        if counts["keyframes"] == 0:
            continue
        loaded = load_map(path, scene.cameras[0])
        assert (len(loaded.keyframes), len(loaded.points)) == (counts["keyframes"], counts["points"])
        assert all(len(p.observations) >= 1 and p.id in loaded.keyframes[k].point_ids
                   for p in loaded.points.values() for k in p.observations)
        sizes.append(counts["keyframes"])
    print(f"{len(saved)} maps saved while mapping, keyframes {sizes}, all loaded whole")
    assert len(sizes) >= 5 and sizes == sorted(sizes)
