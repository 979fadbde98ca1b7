"""The recorder and replay nodes as real processes on a private Zenoh router.

The test process publishes (or subscribes) through its own session; ``artrack record`` and
``artrack replay`` run as child processes; recordings are checked with the package's reader
and with the stock MCAP reader.
"""

from __future__ import annotations

import json
import os
import signal
import threading
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from mcap.decoder import DecoderFactory
from mcap.reader import make_reader

from protocol import CameraInfo, ErrorReport, Header, Image, Message, Pose, decode, encode
from protocol.codec import MEDIA_FRAME
from protocol.schemas import json_schema
from protocol.spatial import Transform
from services.bus.local import LocalBus
from services.bus.pubsub import Publisher, Role
from services.recorder.byte_queue import ByteQueue
from services.recorder.reading import Scan, indexed
from services.recorder.record_node import Tap
from services.recorder.writing import RecordingWriter

from .support import START_S, live_names, states, wait_live, wait_until

pytestmark = pytest.mark.integration

def pose(i: int, target: str = "wand") -> Pose:
    angle = 0.05 * i
    return Pose(header=Header(stamp_ns=1_700_000_000_000_000_000 + i * 10_000_000, frame_id="world", seq=i),
                child_frame_id=target,
                transform=Transform(translation=(0.1 * i, -0.2, 1.0 + 1e-3 * i),
                                    rotation=(0.0, np.sin(angle / 2), 0.0, np.cos(angle / 2))))


def image(i: int) -> Image:
    pixels = np.random.default_rng(i).integers(0, 256, (48, 64), dtype=np.uint8)
    return Image(header=Header(stamp_ns=1_700_000_000_000_000_000 + i * 33_000_000, frame_id="cam0", seq=i),
                 encoding="mono8", data=pixels)


def camera_info(i: int) -> CameraInfo:
    return CameraInfo(header=Header(stamp_ns=1_700_000_000_000_000_000 + i * 33_000_000, frame_id="cam0", seq=i),
                      width=64, height=48, k=(50.0, 0.0, 32.0, 0.0, 50.0, 24.0, 0.0, 0.0, 1.0))


def publish(session, items: list[tuple[str, Message | bytes, Role]], rate_hz: float) -> dict[str, list[bytes]]:
    """Publish ``items`` in order at ``rate_hz`` once every key has a subscriber; the payloads per key."""
    publishers = {}
    for key, message, role in items:
        if isinstance(message, Message) and key not in publishers:
            publishers[key] = Publisher(session, key, type(message), role)
    try:
        wait_until(lambda: all(p.matched() for p in publishers.values()), START_S, "the recorder to subscribe")
        time.sleep(0.2)
        sent: dict[str, list[bytes]] = {}
        due = time.monotonic()
        for key, message, _ in items:
            if isinstance(message, Message):
                publishers[key].put(message)
                sent.setdefault(key, []).append(encode(message))
            else:
                session.put(key, message)
                sent.setdefault(key, []).append(message)
            due += 1 / rate_hz
            time.sleep(max(0.0, due - time.monotonic()))
        return sent
    finally:
        for publisher in publishers.values():
            publisher.close()


def channels(path: Path) -> dict[str, list[bytes]]:
    """Payloads per key, in file order."""
    found: dict[str, list[bytes]] = {}
    for recorded in Scan(path).messages():
        found.setdefault(recorded.channel.topic, []).append(recorded.message.data)
    return found


def stop(proc) -> None:
    """SIGINT, like Ctrl-C; the process must finish cleanly."""
    os.kill(proc.pid, signal.SIGINT)
    assert proc.wait(15) == 0, proc.describe()


class Collector:
    """A subscriber of the test session that keeps ``(key, payload)`` in arrival order."""

    def __init__(self, session, key: str):
        self.received: list[tuple[str, bytes]] = []
        self._lock = threading.Lock()
        self._subscriber = session.declare_subscriber(key, self._on_sample)

    def _on_sample(self, sample) -> None:
        with self._lock:
            self.received.append((str(sample.key_expr), sample.payload.to_bytes()))

    def count(self) -> int:
        with self._lock:
            return len(self.received)

    def close(self) -> None:
        self._subscriber.undeclare()


def recorder_stats(session, keys, at_least: int):
    """The recorder's NodeStats once it has received ``at_least`` messages, else None."""
    found = states(session, keys).get("recorder")
    return found if found is not None and found.received >= at_least else None


class JsonDecoders(DecoderFactory):
    def decoder_for(self, message_encoding, schema):
        return json.loads if message_encoding == "json" else None


def test_record_replay_record_gives_the_same_bytes_on_every_key_in_the_same_order(bus, procs, session, tmp_path):
    first, second = tmp_path / "first.mcap", tmp_path / "second.mcap"
    keys = bus.keys
    junk = f"{keys.prefix}/junk"
    items = []
    for i in range(40):  # frames put blocking: one a busy machine's publisher drops would never reach the recorder
        items += [(keys.pose("wand"), pose(i), Role.RESULT), (keys.image("cam0"), image(i), Role.RESULT),
                  (keys.camera_info("cam0"), camera_info(i), Role.RESULT)]
        if i % 10 == 0:
            items.append((junk, b"not an artrack message %d" % i, Role.RESULT))
    recorder = procs.artrack("record", str(first), name="record-first")
    sent = publish(session, items, rate_hz=400)

    stats = wait_until(lambda: recorder_stats(session, keys, len(items)), START_S, "the recorder to count them all")
    assert (stats.kind, stats.dropped, stats.decode_errors) == ("recorder", 0, 4)  # the junk, counted
    stop(recorder)

    recorded = channels(first)
    assert {k: recorded[k] for k in sent} == sent
    result_keys = {keys.pose("wand"), keys.camera_info("cam0")}  # one QoS: their relative order is kept

    def merged(path: Path) -> list[tuple[str, bytes]]:
        return [(r.channel.topic, r.message.data) for r in Scan(path).messages() if r.channel.topic in result_keys]

    recorder = procs.artrack("record", str(second), name="record-second")
    wait_live(session, keys, {"recorder"}, [recorder])
    replay = procs.run("replay", str(first), "--rate", "4", "--wait", str(START_S))
    assert replay.poll() == 0, replay.describe()
    assert "replayed" in replay.stderr
    stop(recorder)

    replayed = channels(second)
    live_stats = [decode(payload) for payload in replayed[keys.stats("recorder")]]
    assert {s.pid for s in live_stats} == {recorder.pid}  # node health is not replayed by default
    data_keys = [k for k in recorded if "/node/" not in k]
    assert sorted(data_keys) == sorted([*sent])
    assert {k: replayed.get(k) for k in data_keys} == {k: recorded[k] for k in data_keys}
    assert merged(second) == merged(first)

    with open(first, "rb") as f:  # what a stock MCAP reader sees
        reader = make_reader(f, decoder_factories=[JsonDecoders()])
        summary = reader.get_summary()
        by_topic = {c.topic: c for c in summary.channels.values()}
        pose_channel = by_topic[keys.pose("wand")]
        schema = summary.schemas[pose_channel.schema_id]
        assert (pose_channel.message_encoding, schema.name, schema.encoding) == ("json", "artrack.Pose", "jsonschema")
        assert json.loads(schema.data) == json.loads(json.dumps(json_schema(Pose)))
        assert by_topic[keys.image("cam0")].message_encoding == MEDIA_FRAME
        assert (by_topic[junk].schema_id, by_topic[junk].message_encoding) == (0, "application/octet-stream")
        decoded = list(reader.iter_decoded_messages(topics=[keys.pose("wand")]))
        assert [d.decoded_message["header"]["seq"] for d in decoded] == list(range(40))
        assert all(d.message.publish_time == d.decoded_message["header"]["stamp_ns"] for d in decoded)
        assert [d.message.sequence for d in decoded] == list(range(40))

    info = procs.run("info", str(first))
    assert info.poll() == 0, info.describe()
    assert "status     intact" in info.stdout and "indexed (summary present)" in info.stdout
    rows = {line.split()[0]: line.split() for line in info.stdout.splitlines() if line.startswith(keys.prefix)}
    assert rows[keys.pose("wand")][1:4] == ["artrack.Pose", "json", "40"]
    assert rows[keys.image("cam0")][1:4] == ["artrack.Image", MEDIA_FRAME, "40"]
    assert rows[junk][1:4] == ["(raw)", "application/octet-stream", "4"]
    assert "received" in info.stdout and "dropped 0" in info.stdout


def test_kill_9_leaves_a_file_with_every_flushed_message_readable(bus, procs, session, tmp_path):
    out, fixed = tmp_path / "killed.mcap", tmp_path / "fixed.mcap"
    recorder = procs.artrack("record", str(out), "--keys", "pose/**", "--flush", "0.3")
    sent = publish(session, [(bus.keys.pose("wand"), pose(i), Role.RESULT) for i in range(50)], rate_hz=200)
    time.sleep(1.0)  # three flush periods
    os.killpg(recorder.pid, signal.SIGKILL)
    recorder.wait(5)

    scan = Scan(out)
    assert [r.message.data for r in scan.messages()] == sent[bus.keys.pose("wand")]
    assert scan.damage is not None and "not finished" in scan.damage.reason
    assert not indexed(out)

    info = procs.run("info", str(out), "--json", "--recover", str(fixed))
    assert info.poll() == 3, info.describe()
    report = json.loads(info.stdout)
    assert report["messages"] == 50 and report["damage"]["offset"] == out.stat().st_size
    assert report["indexed"] is False
    with open(fixed, "rb") as f:
        assert make_reader(f).get_summary().statistics.message_count == 50
    assert channels(fixed) == sent


@pytest.mark.parametrize(("option", "value", "kind"), [("--split-size", "0.05", "image"),
                                                        ("--split-duration", "0.25", "pose")])
def test_split_options_write_valid_parts_without_losing_or_repeating_a_message(bus, procs, session, tmp_path,
                                                                               option, value, kind):
    key = bus.keys.image("cam0") if kind == "image" else bus.keys.pose("wand")
    make, role = (image, Role.FRAME) if kind == "image" else (pose, Role.RESULT)
    recorder = procs.artrack("record", str(tmp_path / "split.mcap"), "--keys", key, option, value)
    sent = publish(session, [(key, make(i), role) for i in range(60)], rate_hz=100)
    time.sleep(0.3)
    stop(recorder)

    parts = sorted(tmp_path.glob("split*.mcap"))
    assert [p.name for p in parts] == [f"split_{i:03d}.mcap" for i in range(len(parts))]
    assert len(parts) >= 2
    assert all(indexed(p) for p in parts)
    recorded = [r.message for p in parts for r in Scan(p).messages()]
    assert [m.data for m in recorded] == sent[key]
    assert [m.sequence for m in recorded] == list(range(60))


def test_the_recorder_is_listed_as_a_node(bus, procs, session, tmp_path):
    recorder = procs.artrack("record", str(tmp_path / "listed.mcap"), "--name", "rec")
    wait_live(session, bus.keys, {"rec"}, [recorder])
    assert "rec" in live_names(session, bus.keys)
    listed = procs.run("list", "--timeout", "1.0")
    assert any(line.split()[1:3] == ["rec", "recorder"] for line in listed.stdout.splitlines()), listed.stdout
    stop(recorder)
    assert Scan(tmp_path / "listed.mcap").damage is None


def test_a_full_queue_drops_the_newest_arrivals_and_counts_them_without_blocking(bus, session):
    class Node:  # the parts of a node a tap uses; the bus under it is real
        def __init__(self) -> None:
            self.session, self.reports = session, []
            self.host = SimpleNamespace(local=LocalBus())

        def track(self, counter):
            return counter

        def report(self, kind: str, detail: str, key: str) -> None:
            self.reports.append((kind, key))

    node, queue = Node(), ByteQueue(2_000)
    tap = Tap(node, bus.keys.poses(), queue)
    publisher = Publisher(session, bus.keys.pose("wand"), Pose, Role.RESULT)
    try:
        sent = [encode(pose(i)) for i in range(20)]
        for i in range(20):
            publisher.put(pose(i))
    finally:
        publisher.close()
        assert tap.close()  # everything Zenoh had was delivered
    kept = [queue.get(0)[1] for _ in range(len(queue))]
    assert 0 < len(kept) < 20 and kept == sent[: len(kept)]
    counts = tap.counter.snapshot()
    assert (counts.messages, counts.dropped, counts.decode_errors) == (20, 20 - len(kept), 0)
    assert set(node.reports) == {("queue_full", bus.keys.pose("wand"))}


def write_recording(path: Path, messages: list[tuple[str, Message]], spacing_ns: int, flush_every: int) -> None:
    """A recording of ``messages`` whose log times are ``spacing_ns`` apart, flushed into many chunks."""
    writer = RecordingWriter(path)
    for i, (key, message) in enumerate(messages):
        writer.write(key, encode(message), 1_000_000_000 + i * spacing_ns)
        if i % flush_every == flush_every - 1:
            writer.flush()
    writer.close()


def test_replay_of_a_truncated_file_plays_its_intact_part_then_says_where_it_stopped(bus, procs, session, tmp_path):
    full, cut = tmp_path / "full.mcap", tmp_path / "cut.mcap"
    targets = ["a", "b", "c"]
    write_recording(full, [(bus.keys.pose(targets[i % 3]), pose(i, targets[i % 3])) for i in range(300)],
                    spacing_ns=1_000_000, flush_every=20)
    data = full.read_bytes()
    cut.write_bytes(data[: int(len(data) * 0.6)])
    scan = Scan(cut)
    intact = [(r.channel.topic, r.message.data) for r in scan.messages()]
    assert 0 < len(intact) < 300 and scan.damage is not None

    collector = Collector(session, bus.keys.poses())
    try:
        replay = procs.run("replay", str(cut), "--wait", str(START_S))
        assert replay.poll() == 3, replay.describe()
        wait_until(lambda: collector.count() >= len(intact), 5.0, "the replayed messages")
        time.sleep(0.2)
        assert collector.received == intact
    finally:
        collector.close()
    damaged = [line for line in replay.stderr.splitlines() if "is damaged" in line]
    assert len(damaged) == 1, replay.stderr
    assert f"stopped at byte {scan.damage.offset} of {scan.damage.size}: {scan.damage.reason}" in damaged[0]
    assert f"after {len(intact)} intact messages" in damaged[0]


def test_a_paused_replay_steps_and_resumes_on_control_commands(bus, procs, session, tmp_path):
    path = tmp_path / "five.mcap"
    messages = [(bus.keys.pose("wand"), pose(i)) for i in range(5)]
    write_recording(path, messages, spacing_ns=100_000_000, flush_every=5)

    def control(command: str) -> dict:
        answer = procs.run("control", "replay", command)
        assert answer.poll() == 0, answer.describe()
        return json.loads(answer.stdout)

    collector = Collector(session, bus.keys.poses())
    try:
        replay = procs.artrack("replay", str(path), "--paused", "--wait", str(START_S))
        wait_live(session, bus.keys, {"replay"}, [replay])
        status = control("status")
        assert status == {"node": "replay", "path": str(path), "state": "paused", "played": 0, "passes": 0,
                          "position_s": 0.0, "rate": 1.0}
        garbage = {b"cmd=rewind": "neither an artrack frame nor JSON", encode(pose(0)): "not a control request"}
        for payload, reason in garbage.items():
            replies = list(session.get(bus.keys.control("replay"), payload=payload, timeout=5.0))
            assert len(replies) == 1 and replies[0].ok is None
            refusal = decode(replies[0].err.payload.to_bytes())
            assert isinstance(refusal, ErrorReport) and refusal.kind == "bad_request", refusal
            assert reason in refusal.detail, refusal
        time.sleep(0.5)
        assert collector.count() == 0
        stepped = control("step")  # answered once the message went out: the state after the step
        assert (stepped["state"], stepped["played"], stepped["position_s"]) == ("paused", 1, 0.0), stepped
        wait_until(lambda: collector.count() == 1, 5.0, "the stepped message")
        stepped = control("step")
        assert (stepped["state"], stepped["played"], stepped["position_s"]) == ("paused", 2, 0.1), stepped
        wait_until(lambda: collector.count() == 2, 5.0, "the second stepped message")
        time.sleep(0.4)  # more than the recorded gap: still paused
        assert collector.count() == 2
        assert control("resume")["state"] == "playing"
        assert replay.wait(10) == 0, replay.describe()
        wait_until(lambda: collector.count() == 5, 5.0, "the rest of the messages")
        assert collector.received == [(key, encode(message)) for key, message in messages]
    finally:
        collector.close()
    refused = procs.run("control", "replay", "status", "--timeout", "0.5")
    assert refused.poll() == 1 and "no node answered" in refused.stderr


def test_loop_replays_the_window_again_until_stopped(bus, procs, session, tmp_path):
    path = tmp_path / "ten.mcap"
    messages = [(bus.keys.pose("wand"), pose(i)) for i in range(10)]
    write_recording(path, messages, spacing_ns=20_000_000, flush_every=3)
    window = [encode(message) for _, message in messages[3:7]]  # at 60, 80, 100 and 120 ms
    collector = Collector(session, bus.keys.poses())
    try:
        replay = procs.artrack("replay", str(path), "--loop", "--start", "0.05", "--end", "0.12", "--rate", "2",
                               "--wait", str(START_S))
        wait_until(lambda: collector.count() >= 3 * len(window), START_S, "three passes")
        stop(replay)
        payloads = [payload for _, payload in collector.received]
        assert payloads == (window * len(payloads))[: len(payloads)]
    finally:
        collector.close()
    assert "pass(es)" in replay.stderr
