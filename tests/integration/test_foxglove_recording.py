"""``artrack run --record-foxglove``: the Foxglove form written live beside the byte-exact recording, held against
that recording's own export, and a run stopped with Ctrl-C leaving a finished file; an image target's outline in
both, the size of the target the scene renders, and in a recorder's and a Foxglove node's files when they join
the run after the target was published."""

from __future__ import annotations

import os
import signal
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mcap.reader import make_reader

from protocol import ImageTargets, Pose, StaticTransforms, decode
from services.bus.pubsub import Inbox, Role
from services.synthetic.planar_target import PlanarTargetScene
from tests.foxglove_decoding import decoded

from .support import START_S, collect, start_node, wait_live

pytestmark = pytest.mark.integration

FRAMES = 30
IMAGE_TOPIC = "/cam0/image"


def read_foxglove(path: Path) -> tuple[Any, dict[str, list[Any]], list[int]]:
    """The file's summary, its decoded messages by topic (in file order) and their log times in file order."""
    by_topic: dict[str, list[Any]] = defaultdict(list)
    log_times = []
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            assert channel.message_encoding == "protobuf" and schema is not None
            by_topic[channel.topic].append((schema.name, decoded(schema.name, schema.data, message.data)))
            log_times.append(message.log_time)
    return summary, by_topic, log_times


def poses(by_topic: dict[str, list[Any]]) -> dict[str, list[Any]]:
    """The PoseInFrame messages by topic, in stamp order."""
    return {topic: sorted((m for _, m in shown), key=lambda m: m.timestamp.ToNanoseconds())
            for topic, shown in by_topic.items() if shown[0][0] == "foxglove.PoseInFrame"}


def test_a_run_writes_every_frame_and_the_exported_poses_live(procs, tmp_path):
    recorded, live, exported = tmp_path / "run.mcap", tmp_path / "live.mcap", tmp_path / "exported.mcap"
    job = procs.artrack("run", "marker", "--source", "synthetic:markers", "--frames", str(FRAMES), "--record",
                        str(recorded), "--record-foxglove", str(live), name="job")
    assert job.wait(4 * START_S) == 0, job.describe()
    export = procs.run("export", str(recorded), "--format", "foxglove", "-o", str(exported))
    assert export.poll() == 0, export.describe()

    summary, by_topic, log_times = read_foxglove(live)
    assert summary is not None and summary.statistics is not None and summary.chunk_indexes
    assert summary.statistics.message_count == len(log_times) and log_times == sorted(log_times)
    stamps = [m.timestamp.ToNanoseconds() for _, m in by_topic[IMAGE_TOPIC]]
    assert len(stamps) == len(set(stamps)) == FRAMES, len(stamps)
    assert {name for name, _ in by_topic[IMAGE_TOPIC]} == {"foxglove.RawImage"}

    _, exported_by_topic, _ = read_foxglove(exported)
    live_poses, exported_poses = poses(by_topic), poses(exported_by_topic)
    assert live_poses and sum(map(len, live_poses.values())) >= FRAMES, {t: len(p) for t, p in live_poses.items()}
    assert live_poses == exported_poses


def test_a_run_stopped_with_ctrl_c_leaves_a_finished_file(procs, session, bus, tmp_path):
    live = tmp_path / "live.mcap"
    job = procs.artrack("run", "marker", "--source", "synthetic:markers", "--fps", "15",
                        "--record-foxglove", str(live), name="job")
    wait_live(session, bus.keys, {"foxglove", "capture"}, [job])  # the source starts last
    time.sleep(1.5)  # frames on their way
    os.kill(job.pid, signal.SIGINT)
    assert job.wait(START_S) == 0, job.describe()  # a source with no end: stopping it is its end
    summary, by_topic, log_times = read_foxglove(live)
    assert summary is not None and summary.statistics is not None and summary.chunk_indexes, job.describe()
    assert summary.statistics.message_count == len(log_times) > 0
    assert by_topic[IMAGE_TOPIC], sorted(by_topic)


def test_a_features_run_draws_its_target_as_an_outline_of_the_scenes_target_in_the_targets_frame(procs, tmp_path):
    recorded, live, exported = tmp_path / "run.mcap", tmp_path / "live.mcap", tmp_path / "exported.mcap"
    job = procs.artrack("run", "features", "--source", "synthetic:planar_target", "--frames", "10", "--record",
                        str(recorded), "--record-foxglove", str(live), name="job")
    assert job.wait(4 * START_S) == 0, job.describe()
    export = procs.run("export", str(recorded), "--format", "foxglove", "-o", str(exported))
    assert export.poll() == 0, export.describe()
    scene = PlanarTargetScene()
    texel_m = scene.size_m[0] / scene.texture.shape[1]
    for path in (exported, live):
        _, by_topic, _ = read_foxglove(path)
        updates = by_topic["/cam0/target_outlines"]
        assert updates and {name for name, _ in updates} == {"foxglove.SceneUpdate"}, (path, sorted(by_topic))
        (entity,) = updates[-1][1].entities
        assert (entity.id, entity.frame_id, entity.frame_locked) == ("target/planar_target",) * 2 + (True,)
        corners = np.array([[p.x, p.y, p.z] for p in entity.lines[0].points])
        assert corners.shape == (4, 3) and np.all(corners[:, 2] == 0), corners
        across, down = corners[1] - corners[0], corners[3] - corners[0]
        assert np.linalg.norm(across) == pytest.approx(scene.size_m[0], abs=1e-9), corners
        assert np.linalg.norm(down) == pytest.approx(scene.size_m[1], abs=texel_m), corners
        np.testing.assert_allclose(corners.mean(axis=0), 0.0, atol=1e-12)  # the target frame's origin: the centre
        placed = [t for _, tf in by_topic["/tf"] for t in tf.transforms if t.child_frame_id == entity.frame_id]
        assert placed and {t.parent_frame_id for t in placed} == {"cam0"}, path


def test_a_recorder_and_a_foxglove_node_joining_a_running_features_run_ask_for_its_targets(procs, session, bus,
                                                                                           tmp_path):
    job = procs.artrack("run", "features", "--source", "synthetic:planar_target", "--fps", "10", name="job")
    poses = Inbox(session, bus.keys.pose("cam0/target/planar_target"), Pose, Role.RESULT)
    collect(poses, 1, 4 * START_S)  # the node published its targets before its first poses
    recording, live = tmp_path / "late.mcap", tmp_path / "late-foxglove.mcap"
    recorder = start_node(procs, "recorder", "late-recorder", out=str(recording), keys=["cam0/targets", "tf_static/*"])
    foxglove = start_node(procs, "foxglove", "late-foxglove", serve=False, mcap=str(live))
    wait_live(session, bus.keys, {"late-recorder", "late-foxglove"}, [job, recorder, foxglove])
    time.sleep(1.0)  # answers on their way
    for proc in (recorder, foxglove):
        os.kill(proc.pid, signal.SIGINT)
        assert proc.wait(START_S) == 0, proc.describe()
    with open(recording, "rb") as f:
        kept = [(channel.topic, decode(message.data)) for _, channel, message in make_reader(f).iter_messages()]
    described = [m for topic, m in kept if topic == bus.keys.targets("cam0")]
    assert described and all(isinstance(m, ImageTargets) for m in described), [topic for topic, _ in kept]
    assert [t.name for t in described[0].targets] == ["planar_target"]
    assert any(isinstance(m, StaticTransforms) for _, m in kept), [topic for topic, _ in kept]
    _, by_topic, _ = read_foxglove(live)
    assert by_topic["/cam0/target_outlines"] and by_topic["/tf_static"], sorted(by_topic)
