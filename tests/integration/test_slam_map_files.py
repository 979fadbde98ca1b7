"""``artrack run slam`` with map files: a run saves its map as the node stops, a second run of the same
frames localises in it without changing it; map files and options that cannot work are refused before any
process starts (how long that takes is the ``refusals`` benchmark's), and a map made for another camera is
refused by the running node, which goes on."""

from __future__ import annotations

import dataclasses
import json
import os
import signal

import numpy as np
import pytest

from protocol.message import Header
from protocol.poses import Pose
from protocol.sensors import CameraInfo, Image
from protocol.tracking_state import TrackingState
from services.bus.pubsub import Inbox, Publisher, Role
from services.convert import camera_info
from services.slam.map.file import read_header
from services.slam.system import SlamSystem
from tests.integration.support import START_S, STOP_S, collect, start_node, states, wait_live, wait_until
from tests.integration.test_marker_pipeline import recorded
from tests.slam_passes import room_frames, room_scene

pytestmark = pytest.mark.integration

FRAMES = 90
KEY = "pose/slam/cam0"
MARGIN_M = 0.005
"""How much worse than the mapping run the localising run's ATE may be (metres of the room)."""


def _run(procs, *options: str):
    """The room on the scene's own clock (keyframes are spaced in time), so runs do not depend on the machine's load."""
    job = procs.artrack("run", "slam", "--source", "synthetic:room", "--frames", str(FRAMES), "--depth", str(FRAMES),
                        "--stamps", "source", *options, name="job")
    assert job.wait(8 * START_S) == 0, job.describe()
    return job


def _poses_and_keyframes(out) -> tuple[list[Pose], list]:
    messages = recorded(out)
    prefix = next(key for key in messages if key.endswith("/cam0/image")).removesuffix("/cam0/image")
    return messages[f"{prefix}/{KEY}"], messages[f"{prefix}/cam0/keyframes"]


def _ate_m(procs, out) -> tuple[int, float]:
    scored = procs.run("eval", str(out), str(out), "--est-key", KEY, "--gt-key", "cam0/truth", "--gt-child", "cam0",
                       "--align", "sim3", "--json")
    assert scored.poll() == 0, scored.describe()
    figures = json.loads(scored.stdout)
    return figures["matched"], figures["ate_m"]["rmse"]


def test_a_saved_map_localises_a_second_run_of_the_same_frames(procs, tmp_path):
    map_path, first_out, second_out = tmp_path / "room.map.npz", tmp_path / "first.mcap", tmp_path / "second.mcap"
    first = _run(procs, "--mapping", "inline", "--save-map", str(map_path), "--record", str(first_out))
    assert f"saved to {map_path}" in first.stderr, first.describe()
    header = read_header(map_path)
    first_poses, first_keyframes = _poses_and_keyframes(first_out)
    assert header["counts"]["keyframes"] == len(first_keyframes[-1].ids) >= 2
    first_matched, first_ate = _ate_m(procs, first_out)

    _run(procs, "--map", str(map_path), "--localisation-only", "--record", str(second_out))
    poses, keyframes = _poses_and_keyframes(second_out)
    assert [p.header.seq for p in poses] == list(range(FRAMES))
    states_seen = [p.state for p in poses]
    assert TrackingState.INITIALISING not in states_seen, states_seen  # the map is there from the first frame
    first = states_seen.index(TrackingState.TRACKING)
    assert first < 5 and all(s is TrackingState.TRACKING for s in states_seen[first:]), states_seen
    assert all(np.allclose(k.poses, first_keyframes[-1].poses, atol=1e-9) for k in keyframes)  # the map never moved
    matched, ate = _ate_m(procs, second_out)
    assert matched == FRAMES - first and matched > first_matched
    print(f"first run: ATE {first_ate * 100:.2f} cm over {first_matched} frames, {header['counts']['keyframes']} "
          f"keyframes; localising run: {ate * 100:.2f} cm over {matched} frames (tracked from frame {first})")
    assert ate <= first_ate + MARGIN_M, (ate, first_ate)


@pytest.mark.parametrize(("options", "expected"), [
    (["--map", "{garbage}"], "nodes.slam-cam0: map file {garbage}: not a readable map file"),
    (["--map", "{missing}"], "nodes.slam-cam0: map file {missing}: no such file"),
    (["--localisation-only"], "nodes.slam-cam0: localisation_only needs a map to localise in (map, --map)"),
    (["--save-map", "/no/such/folder/room.map.npz"], "nodes.slam-cam0: cannot save the map to "
                                                     "/no/such/folder/room.map.npz: no folder /no/such/folder"),
    (["--save-map", "{folder}"], "nodes.slam-cam0: cannot save the map to {folder}: a folder"),
], ids=["garbage-map", "missing-map", "localisation-only-without-map", "save-map-in-no-folder", "save-map-a-folder"])
def test_run_refuses_map_files_and_options_that_cannot_work_before_starting(procs, tmp_path, options, expected):
    garbage, missing = tmp_path / "garbage.npz", tmp_path / "missing.npz"
    garbage.write_bytes(b"not a map, " * 100)
    paths = {"garbage": garbage, "missing": missing, "folder": tmp_path}
    job = procs.run("run", "slam", "--source", "synthetic:room", "--frames", "5",
                    *[o.format(**paths) for o in options])
    assert job.poll() == 2, job.describe()
    lines = [line for line in job.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and expected.format(**paths) in lines[0], job.stderr


def test_the_node_goes_on_past_a_map_of_another_camera_and_says_once_when_its_map_cannot_be_saved(
        bus, procs, session, tmp_path):
    scene = room_scene()
    map_path, gone = tmp_path / "room.map.npz", tmp_path / "gone"
    gone.mkdir()
    system = SlamSystem(scene.cameras[0], mapping="inline", save_path=map_path)
    for stamp_ns, image, _ in room_frames(scene, range(20)):
        system.process(stamp_ns, image)
    system.close()
    keys = bus.keys
    poses = Inbox(session, keys.slam_pose("cam0"), Pose, Role.RESULT)
    frames = Publisher(session, keys.image("cam0"), Image, Role.RESULT)
    infos = Publisher(session, keys.camera_info("cam0"), CameraInfo, Role.RESULT)
    seen: dict[int, Pose] = {}

    def send(seq: int, index: int) -> Pose:
        image = scene.render(index).images["cam0"]
        frames.put(Image(header=Header(stamp_ns=1_000 + seq, frame_id="cam0", seq=seq), encoding="mono8", data=image))
        got = collect(poses, lambda got: any(p.header.seq == seq for p in got))
        seen.update((p.header.seq, p) for p in got)
        return seen[seq]

    def calibrate(camera, count: int) -> None:
        infos.put(camera_info(Header(stamp_ns=1_000, frame_id="cam0"), camera))
        wait_until(lambda: (s := states(session, keys).get("slam")) and sum(
            x.messages for x in s.streams if x.key == keys.camera_info("cam0") and x.direction == "in") == count,
            START_S, f"CameraInfo {count} to arrive")

    try:
        node = start_node(procs, "slam", "slam", depth=10, map=str(map_path), localisation_only=True,
                          mapping="inline", save_map=str(gone / "saved.map.npz"))
        wait_live(session, keys, {"slam"}, [node])
        wait_until(lambda: frames.matched() and infos.matched(), START_S, "the node to subscribe")
        camera = scene.cameras[0]
        other = dataclasses.replace(camera, K=camera.K * [[1.05, 1, 1], [1, 1.05, 1], [1, 1, 1]])  # fx, fy 5 % up
        calibrate(other, 1)
        refused = [(send(seq, 10).state, seen[seq].reason) for seq in range(3)]
        assert refused == [(TrackingState.LOST, "map_refused")] * 3, refused
        assert node.poll() is None, node.describe()
        refusals = [line for line in node.stderr.splitlines() if "ERROR" in line]  # once, not once a frame
        assert len(refusals) == 1 and f"map file {map_path}: made for another camera matrix" in refusals[0], \
            node.stderr
        calibrate(camera, 2)  # taken in after the next frame, which is refused still
        after = [send(seq, index) for seq, index in ((3, 10), (4, 10), (5, 11), (6, 12))]
        assert after[0].reason == "map_refused" and after[-1].state is TrackingState.TRACKING, \
            [(p.state, p.reason) for p in after]
        stats = wait_until(lambda: (s := states(session, keys).get("slam")) and s.processed == 7 and s, START_S,
                           "the node to count 7 frames")
        assert stats.skipped == {"map_refused": 4}, stats.skipped

        gone.rmdir()  # the map is saved as the node stops: it cannot be, and the node says so in one line
        os.kill(node.pid, signal.SIGTERM)
        assert node.wait(STOP_S) == 0, node.describe()
        unsaved = [line for line in node.stderr.splitlines() if "saved.map.npz" in line]
        assert len(unsaved) == 1 and "ERROR" in unsaved[0] and "cannot be written" in unsaved[0], node.stderr
    finally:
        infos.close()
        frames.close()
        poses.close()
