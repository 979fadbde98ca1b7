"""Recording files: the writer, the damage-tolerant reader, recover, split parts, the arrival queue."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

from protocol import Header, Image, Pose, encode
from protocol.codec import MEDIA_FRAME
from protocol.schemas import json_schema
from services.cli import main
from services.recorder.byte_queue import ByteQueue
from services.recorder.reading import EXIT_DAMAGED, NotMcap, Scan, indexed, recover
from services.recorder.writing import RECORDER_METADATA, RECORDING_METADATA, RecordingWriter, Split, part_path

T0 = 1_000_000_000


def traffic(n: int) -> list[tuple[str, bytes]]:
    """Poses, images and raw bytes on a few keys; one key carries both a Pose and raw bytes."""
    items = []
    for i in range(n):
        stamp = 5_000 + i
        items.append(("ar/r/pose/a", encode(Pose(header=Header(stamp_ns=stamp, seq=i), child_frame_id="a"))))
        pixels = np.random.default_rng(i).integers(0, 256, (24, 32), dtype=np.uint8)
        items.append(("ar/r/cam0/image", encode(Image(header=Header(stamp_ns=stamp, seq=i), encoding="mono8",
                                                      data=pixels))))
        if i % 3 == 0:
            items.append(("ar/r/pose/a", b"raw bytes %d" % i))
    return items


def write(path: Path, items: list[tuple[str, bytes]], *, flush_every: int = 0, **options) -> RecordingWriter:
    """Write ``items`` 1 ms apart in log time, flushing every ``flush_every`` items (0: never)."""
    writer = RecordingWriter(path, **options)
    for i, (key, payload) in enumerate(items):
        writer.write(key, payload, T0 + i * 1_000_000)
        if flush_every and i % flush_every == flush_every - 1:
            writer.flush()
    writer.close()
    return writer


def read(path: Path) -> list[tuple[str, bytes]]:
    return [(r.channel.topic, r.message.data) for r in Scan(path).messages()]


def test_payloads_come_back_byte_for_byte_in_order_with_schemas_and_stamps(tmp_path):
    path = tmp_path / "rec.mcap"
    items = traffic(30)
    write(path, items, metadata={"namespace": "ar", "rig": "r"})
    scan = Scan(path)
    recorded = list(scan.messages())
    assert [(r.channel.topic, r.message.data) for r in recorded] == items
    assert scan.damage is None and indexed(path)
    assert scan.metadata[RECORDING_METADATA]["rig"] == "r" and scan.metadata[RECORDING_METADATA]["part"] == "0"
    assert scan.metadata[RECORDER_METADATA]["messages"] == str(len(items))

    channels = {(r.channel.topic, r.schema.name if r.schema else None): r.channel for r in recorded}
    assert set(channels) == {("ar/r/pose/a", "artrack.Pose"), ("ar/r/pose/a", None),
                             ("ar/r/cam0/image", "artrack.Image")}
    assert channels["ar/r/pose/a", "artrack.Pose"].message_encoding == "json"
    assert channels["ar/r/cam0/image", "artrack.Image"].message_encoding == MEDIA_FRAME
    assert channels["ar/r/cam0/image", "artrack.Image"].metadata == {"artrack.layout": "frame", "artrack.version": "1"}
    raw = channels["ar/r/pose/a", None]
    assert (raw.schema_id, raw.message_encoding, raw.metadata["artrack.layout"]) == (0, "application/octet-stream",
                                                                                     "raw")
    pose_schema = next(r.schema for r in recorded if r.schema and r.schema.name == "artrack.Pose")
    assert pose_schema.encoding == "jsonschema" and json.loads(pose_schema.data) == json_schema(Pose)

    for r in recorded:
        expected = json.loads(r.message.data)["header"]["stamp_ns"] if r.channel.message_encoding == "json" else None
        if expected is not None:
            assert r.message.publish_time == expected
        if r.schema is None:
            assert r.message.publish_time == r.message.log_time
    assert [r.message.sequence for r in recorded if r.channel.topic == "ar/r/cam0/image"] == list(range(30))


def test_an_empty_recording_is_a_valid_file(tmp_path):
    path = tmp_path / "empty.mcap"
    RecordingWriter(path).close()
    assert indexed(path) and read(path) == [] and Scan(path).damage is None


DATA_END_HEAD = 9
"""The DataEnd record's opcode and length: a file cut before they are whole ended unfinished."""


def test_a_file_cut_anywhere_yields_an_intact_prefix_and_recover_indexes_it(tmp_path):
    path = tmp_path / "rec.mcap"
    items = traffic(12)
    write(path, items, flush_every=4)
    data = path.read_bytes()
    data_end = data.rindex(b"\x0f" + (4).to_bytes(8, "little"))  # the DataEnd record: opcode, length 4
    cut, fixed = tmp_path / "cut.mcap", tmp_path / "fixed.mcap"
    previous = 0
    for size in [*range(8, len(data), 37), *range(data_end - 1, data_end + DATA_END_HEAD + 2)]:
        cut.write_bytes(data[:size])
        scan = Scan(cut)
        got = [(r.channel.topic, r.message.data) for r in scan.messages()]
        assert got == items[: len(got)] and len(got) >= previous
        previous = len(got)
        assert (scan.damage is None) == (size >= data_end + DATA_END_HEAD), size
        if scan.damage is not None:
            assert 8 <= scan.damage.offset <= size and scan.damage.size == size
        fixed.unlink(missing_ok=True)
        recovered = recover(cut, fixed)
        assert recovered.messages == len(got) and recovered.damage == scan.damage
        assert indexed(fixed) and read(fixed) == got
    assert previous == len(items)


def test_recover_never_overwrites_a_file_least_of_all_the_recording_it_reads(tmp_path, capsys):
    path = tmp_path / "rec.mcap"
    write(path, traffic(6), flush_every=2)
    cut, kept = tmp_path / "cut.mcap", tmp_path / "kept.mcap"
    cut.write_bytes(path.read_bytes()[: path.stat().st_size // 3])
    kept.write_bytes(b"kept")
    before = cut.read_bytes()
    for target in (kept, cut):
        assert main(["info", str(cut), "--recover", str(target)]) == 2
        assert f"{target} exists: choose another name" in capsys.readouterr().err
    assert kept.read_bytes() == b"kept" and cut.read_bytes() == before
    with pytest.raises(FileExistsError):
        recover(cut, kept)
    assert main(["info", str(cut), "--recover", str(tmp_path / "fixed.mcap")]) == EXIT_DAMAGED
    assert indexed(tmp_path / "fixed.mcap")


def test_a_corrupt_chunk_ends_the_intact_part_where_it_starts(tmp_path):
    path = tmp_path / "rec.mcap"
    items = traffic(12)
    write(path, items, flush_every=4)
    data = bytearray(path.read_bytes())
    chunks = [i for i in range(len(data)) if data[i] == 0x06 and data[i + 41: i + 45] == b"zstd"]
    second = chunks[1]  # opcode(1) length(8) start(8) end(8) size(8) crc(4) compression length(4) = 41
    data[second + 60] ^= 0xFF
    (tmp_path / "bad.mcap").write_bytes(bytes(data))
    scan = Scan(tmp_path / "bad.mcap")
    got = [(r.channel.topic, r.message.data) for r in scan.messages()]
    assert got == items[: len(got)] and 0 < len(got) < len(items)
    assert scan.damage.offset == second and "corrupt zstd chunk" in scan.damage.reason


def test_what_is_not_mcap_is_refused_at_once(tmp_path):
    (tmp_path / "text.mcap").write_text("hello")
    with pytest.raises(NotMcap, match="not an MCAP file"):
        Scan(tmp_path / "text.mcap")
    with pytest.raises(NotMcap, match="cannot read"):
        Scan(tmp_path / "missing.mcap")


@pytest.mark.parametrize("split", [Split(size_bytes=10_000), Split(duration_ns=7_000_000)])
def test_split_parts_are_complete_files_holding_every_message_once(tmp_path, split):
    out = tmp_path / "rec.mcap"
    items = traffic(30)
    writer = write(out, items, split=split, compression="lz4")
    assert writer.files == [part_path(out, i) for i in range(len(writer.files))] and len(writer.files) >= 3
    assert not out.exists() and writer.files[0].name == "rec_000.mcap"
    assert [item for part in writer.files for item in read(part)] == items
    for index, part in enumerate(writer.files):
        assert indexed(part) and Scan(part).damage is None
        with open(part, "rb") as f:
            reader = make_reader(f)
            assert {m.name: m.metadata for m in reader.iter_metadata()}[RECORDING_METADATA]["part"] == str(index)
            if split.size_bytes is not None:
                assert part.stat().st_size < split.size_bytes + 8_000  # one image and the summary over at most
            else:
                stats = reader.get_summary().statistics
                assert stats.message_end_time - stats.message_start_time < split.duration_ns
    sequences = [r.message.sequence for part in writer.files for r in Scan(part).messages()
                 if r.channel.topic == "ar/r/cam0/image"]
    assert sequences == list(range(30))


def test_the_queue_keeps_order_and_refuses_what_does_not_fit():
    queue: ByteQueue[str] = ByteQueue(100)
    assert queue.put("a", 60) and queue.put("b", 40)
    assert not queue.put("c", 1)  # full: refused, not blocking
    assert (len(queue), queue.nbytes) == (2, 100)
    assert queue.get(0) == "a" and queue.get(0) == "b" and queue.get(0.01) is None
    assert queue.put("huge", 1000)  # larger than the capacity, but the queue was empty
    assert not queue.put("d", 1)
    assert queue.get(0) == "huge" and queue.nbytes == 0
