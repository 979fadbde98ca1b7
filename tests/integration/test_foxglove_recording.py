"""``artrack run --record-foxglove``: the Foxglove form written live beside the byte-exact recording, held against
that recording's own export, and a run stopped with Ctrl-C leaving a finished file."""

from __future__ import annotations

import os
import signal
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

import pytest
from mcap.reader import make_reader

from tests.foxglove_decoding import decoded

from .support import START_S, wait_live

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
