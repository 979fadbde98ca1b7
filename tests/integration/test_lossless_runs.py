"""Lossless runs of finite sources: every node takes every frame, so the results do not depend on the
machine's load. Each tracker runs the same scene twice, once on an idle machine and once while busy
processes hog every core, and the recorded results must be the same bytes."""

from __future__ import annotations

import contextlib
import json

import numpy as np
import pytest
from mcap.reader import make_reader

from protocol.codec import decode, encode
from tests.integration.support import START_S
from tests.load import busy

pytestmark = pytest.mark.integration

LOSSLESS = "every frame accounted for"
STREAMS_LEFT_OUT = ("/image", "/camera_info", "/truth", "/timings", "/targets")
"""Inputs (the same by construction), stage timings (wall-clock durations) and static data (answered to the
recorder as well as published, as it comes) are not compared."""

TRACKERS = {
    "marker": ("synthetic:markers", 24, ()),
    "stereo": ("synthetic:ir_rig", 24, ()),
    "features": ("synthetic:planar_target", 20, ()),
    "slam": ("synthetic:room", 30, ("--mapping", "inline", "--depth", "30")),
}


def results(path) -> dict[str, list[bytes]]:
    """The payloads of every result key of a recording (node health and inputs left out), in log order."""
    found: dict[str, list[bytes]] = {}
    with open(path, "rb") as f:
        for _, channel, message in make_reader(f).iter_messages(log_time_order=True):
            if "/node/" in channel.topic or "/tf_static/" in channel.topic or channel.topic.endswith(STREAMS_LEFT_OUT):
                continue
            found.setdefault(channel.topic, []).append(message.data)
    return found


def run(procs, tmp_path, tracker: str, name: str):
    source, frames, options = TRACKERS[tracker]
    out = tmp_path / f"{name}.mcap"
    job = procs.artrack("run", tracker, "--source", source, "--frames", str(frames), "--fps", "0",
                        "--stamps", "source", *options, "--record", str(out), name=name)
    assert job.wait(12 * START_S) == 0, job.describe()
    last = [line for line in job.stderr.splitlines() if line.strip()][-1]
    assert LOSSLESS in last, job.describe()
    return results(out)


@pytest.mark.parametrize("tracker", sorted(TRACKERS))
def test_a_lossless_run_gives_the_same_results_idle_and_with_every_core_busy(procs, tmp_path, tracker):
    idle = run(procs, tmp_path, tracker, "idle")
    with busy():
        loaded = run(procs, tmp_path, tracker, "loaded")
    assert idle, "the run published no results"
    assert sorted(idle) == sorted(loaded)
    for key in idle:
        assert len(idle[key]) == len(loaded[key]), key
        assert idle[key] == loaded[key], f"{key}: results differ between the idle and the loaded run"


HELD_FPS = 1000
"""A pace no stereo pipeline keeps on this machine: the source is held back by the nodes at nearly every frame."""


def shifted(path, stamp0: int) -> dict[str, list[bytes]]:
    """``results`` of ``path`` with every header stamp taken as its distance from ``stamp0``."""
    moved = {}
    for key, payloads in results(path).items():
        moved[key] = []
        for payload in payloads:
            message = decode(payload)
            header = message.header.model_copy(update={"stamp_ns": message.header.stamp_ns - stamp0})
            moved[key].append(encode(message.model_copy(update={"header": header})))
    return moved


def frame_stamps(path) -> np.ndarray:
    """(N,) int64 stamps of the ``cam0`` images of a recording, in the order they were recorded."""
    with open(path, "rb") as f:
        return np.array([decode(message.data).header.stamp_ns for _, channel, message
                         in make_reader(f).iter_messages(log_time_order=True) if channel.topic.endswith("cam0/image")])


def test_a_held_back_lossless_source_stamps_its_frames_on_its_own_clock_idle_and_busy(procs, tmp_path):
    """The source waits for the nodes at nearly every frame; its stamps, and so the results, do not show it,
    and a replay of the run restamps its frames on the recording's own clock alike."""
    source, frames, _ = TRACKERS["stereo"]
    runs = {}
    for name in ("idle", "loaded"):
        out = tmp_path / f"{name}.mcap"
        with busy() if name == "loaded" else contextlib.nullcontext():
            job = procs.artrack("run", "stereo", "--source", source, "--frames", str(frames), "--fps", str(HELD_FPS),
                                "--record", str(out), name=name)
            assert job.wait(12 * START_S) == 0, job.describe()
        assert LOSSLESS in job.stderr.strip().splitlines()[-1], job.describe()
        stamps = frame_stamps(out)
        assert len(stamps) == frames and set(np.diff(stamps).tolist()) == {1_000_000_000 // HELD_FPS}, stamps
        runs[name] = shifted(out, int(stamps[0]))
    assert runs["idle"] and sorted(runs["idle"]) == sorted(runs["loaded"])
    for key, idle in runs["idle"].items():
        assert idle == runs["loaded"][key], f"{key}: results differ between the idle and the loaded run"
    replayed = tmp_path / "replayed.mcap"
    job = procs.artrack("run", "stereo", "--source", f"recording:{tmp_path / 'loaded.mcap'}", "--record",
                        str(replayed), name="replay")
    assert job.wait(12 * START_S) == 0, job.describe()
    assert LOSSLESS in job.stderr.strip().splitlines()[-1], job.describe()
    stamps = frame_stamps(replayed)
    assert len(stamps) == frames and set(np.diff(stamps).tolist()) == {1_000_000_000 // HELD_FPS}, stamps


SLAM_FRAMES = 90
"""One run in the suite; ``python -m tests.bench lossless`` makes ten (docs/benchmarks.md)."""


def test_slam_with_its_mapping_process_poses_every_frame_within_its_bar_with_every_core_busy(procs, bus, tmp_path):
    out = tmp_path / "slam.mcap"
    with busy():
        job = procs.artrack("run", "slam", "--source", "synthetic:room", "--frames", str(SLAM_FRAMES),
                            "--stamps", "source", "--record", str(out), name="slam")
        assert job.wait(12 * START_S) == 0, job.describe()
    assert LOSSLESS in job.stderr.strip().splitlines()[-1], job.describe()
    poses = results(out)[f"{bus.config.keys.prefix}/pose/slam/cam0"]
    assert len(poses) == SLAM_FRAMES, job.describe()
    scored = procs.run("eval", str(out), str(out), "--est-key", "pose/slam/cam0", "--gt-key", "cam0/truth",
                       "--gt-child", "cam0", "--align", "sim3", "--json")
    assert scored.poll() == 0, scored.describe()
    assert json.loads(scored.stdout)["ate_m"]["rmse"] <= 0.05, scored.stdout
