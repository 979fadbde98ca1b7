"""``artrack info`` and ``artrack export`` as processes, on recordings written for the test (no bus)."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from protocol import FrameTransform, GroundTruth, Header, Pose, encode
from protocol.spatial import Transform
from services.recorder.reading import Scan
from services.recorder.writing import RecordingWriter

pytestmark = pytest.mark.integration

PREFIX = "ar/lab"


def artrack(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "services.cli", *args], capture_output=True, text=True, timeout=60)


def poses(n: int) -> list[Pose]:
    return [Pose(header=Header(stamp_ns=1_700_000_000_123_456_789 + i * 33_333_333, frame_id="world", seq=i),
                 child_frame_id="body/wand",
                 transform=Transform(translation=(0.1 * i, -1 / 3, 2.0 + i * 1e-7),
                                     rotation=(math.sin(0.01 * i), 0.0, 0.0, math.cos(0.01 * i))))
            for i in range(n)]


@pytest.fixture
def recording(tmp_path) -> Path:
    """Poses on ``pose/wand`` and two-body ground truth on ``cam0/truth`` of rig ``lab``, many chunks."""
    path = tmp_path / "session.mcap"
    writer = RecordingWriter(path, metadata={"namespace": "ar", "rig": "lab"})
    for i, pose in enumerate(poses(60)):
        truth = GroundTruth(header=pose.header, transforms=(
            FrameTransform(parent_frame="world", child_frame="body/wand", transform=pose.transform),
            FrameTransform(parent_frame="world", child_frame="cam0", transform=Transform())))
        writer.write(f"{PREFIX}/pose/wand", encode(pose), 2_000_000_000 + i * 33_000_000)
        writer.write(f"{PREFIX}/cam0/truth", encode(truth), 2_000_000_000 + i * 33_000_000 + 1)
        if i % 10 == 9:
            writer.flush()
    writer.close()
    return path


def test_export_tum_parses_back_to_the_recorded_poses(recording, tmp_path):
    out = tmp_path / "wand.tum"
    done = artrack("export", str(recording), "--key", "pose/wand", "--format", "tum", "-o", str(out))
    assert done.returncode == 0, done.stderr
    table = np.loadtxt(out)  # how evo reads a TUM file
    expected = poses(60)
    assert table.shape == (60, 8)
    np.testing.assert_array_equal(table[:, 1:4], [p.transform.translation for p in expected])
    np.testing.assert_array_equal(table[:, 4:8], [p.transform.rotation for p in expected])
    np.testing.assert_allclose(table[:, 0], [p.header.stamp_ns / 1e9 for p in expected], rtol=0, atol=1e-6)
    stamps = [line.split()[0] for line in out.read_text().splitlines()]
    assert [int(s.replace(".", "")) for s in stamps] == [p.header.stamp_ns for p in expected]  # exact to the ns

    truth = artrack("export", str(recording), "--key", f"{PREFIX}/cam0/truth", "--format", "tum",
                    "--child", "body/wand")
    assert truth.returncode == 0, truth.stderr
    assert truth.stdout == out.read_text()


def test_export_refuses_what_does_not_fit_before_writing_anything(recording, tmp_path):
    out = tmp_path / "never.tum"
    missing = artrack("export", str(recording), "--key", "pose/nobody", "--format", "tum", "-o", str(out))
    assert missing.returncode == 2
    assert "no key 'pose/nobody'" in missing.stderr and f"{PREFIX}/pose/wand" in missing.stderr
    assert not out.exists()
    unchosen = artrack("export", str(recording), "--key", "cam0/truth", "--format", "tum", "-o", str(out))
    assert unchosen.returncode == 2 and "--child" in unchosen.stderr and "body/wand, cam0" in unchosen.stderr
    assert not out.exists()
    not_mcap = artrack("export", str(out.with_suffix(".txt")), "--key", "x", "--format", "csv")
    assert not_mcap.returncode == 2 and "cannot read" in not_mcap.stderr


def test_export_of_a_key_expression_writes_one_file_per_matching_key(tmp_path):
    path = tmp_path / "markers.mcap"
    writer = RecordingWriter(path, metadata={"namespace": "ar", "rig": "lab"})
    wanted = {"pose/cam0/marker/3": poses(5), "pose/cam0/marker/4": poses(3)}
    for key, sent in [*wanted.items(), ("pose/cam1/marker/3", poses(2))]:
        for i, pose in enumerate(sent):
            writer.write(f"{PREFIX}/{key}", encode(pose), 1_000 + i)
    writer.close()
    out = tmp_path / "out"
    done = artrack("export", str(path), "--key", f"{PREFIX}/pose/cam0/**", "--format", "tum", "-o", str(out))
    assert done.returncode == 0, done.stderr
    written = sorted(p.relative_to(out).as_posix() for p in out.rglob("*") if p.is_file())
    assert written == ["pose/cam0/marker/3.tum", "pose/cam0/marker/4.tum"]
    for key, sent in wanted.items():
        table = np.loadtxt(out / f"{key}.tum", ndmin=2)
        np.testing.assert_array_equal(table[:, 1:4], [p.transform.translation for p in sent])
        assert f"wrote {out / key}.tum: {len(sent)} rows of {PREFIX}/{key}" in done.stderr
    relative = artrack("export", str(path), "--key", "pose/*/marker/3", "--format", "jsonl", "-o", str(out))
    assert relative.returncode == 0, relative.stderr
    assert {p.name for p in out.rglob("*.jsonl")} == {"3.jsonl"} and (out / "pose/cam1/marker/3.jsonl").is_file()
    none = artrack("export", str(path), "--key", "pose/cam9/**", "--format", "tum", "-o", str(out))
    assert none.returncode == 2 and "no key matches 'pose/cam9/**'" in none.stderr
    assert none.stderr.count("\n") == 1, none.stderr


def test_export_keeps_existing_files_unless_forced(recording, tmp_path):
    out = tmp_path / "wand.tum"
    out.write_text("mine\n")
    kept = artrack("export", str(recording), "--key", "pose/wand", "--format", "tum", "-o", str(out))
    assert kept.returncode == 2 and kept.stderr.strip().endswith(f"{out} exists: give --force to overwrite it")
    assert out.read_text() == "mine\n"
    folder = tmp_path / "all"
    (folder / "pose").mkdir(parents=True)
    (folder / "pose" / "wand.tum").write_text("mine\n")
    expression = artrack("export", str(recording), "--key", "pose/*", "--format", "tum", "-o", str(folder))
    assert expression.returncode == 2 and f"{folder / 'pose' / 'wand.tum'} exists" in expression.stderr
    assert (folder / "pose" / "wand.tum").read_text() == "mine\n"
    forced = artrack("export", str(recording), "--key", "pose/wand", "--format", "tum", "-o", str(out), "--force")
    assert forced.returncode == 0, forced.stderr
    assert len(out.read_text().splitlines()) == 60


def test_export_jsonl_and_csv_carry_every_message(recording):
    lines = artrack("export", str(recording), "--key", "pose/wand", "--format", "jsonl")
    assert lines.returncode == 0, lines.stderr
    rows = [json.loads(line) for line in lines.stdout.splitlines()]
    assert [r["header"]["seq"] for r in rows] == list(range(60))
    assert {r["key"] for r in rows} == {f"{PREFIX}/pose/wand"} and rows[0]["schema"] == "artrack.Pose"
    table = artrack("export", str(recording), "--key", "pose/wand", "--format", "csv")
    assert table.returncode == 0, table.stderr
    header, *body = table.stdout.splitlines()
    columns = header.split(",")
    assert columns[:2] == ["received_ns", "schema"] and "transform.translation.0" in columns
    assert len(body) == 60
    assert float(body[7].split(",")[columns.index("transform.translation.0")]) == poses(60)[7].transform.translation[0]


def test_info_and_export_of_a_truncated_file_report_its_intact_part(recording, tmp_path):
    cut = tmp_path / "cut.mcap"
    data = recording.read_bytes()
    cut.write_bytes(data[: len(data) // 2])
    intact = sum(1 for r in Scan(cut).messages() if r.channel.topic.endswith("pose/wand"))
    assert 0 < intact < 60

    info = artrack("info", str(cut))
    assert info.returncode == 3, info.stderr
    assert "DAMAGED: stopped at byte" in info.stdout and "not indexed" in info.stdout
    assert "not finished (no artrack.recorder record)" in info.stdout
    row = next(line.split() for line in info.stdout.splitlines() if line.startswith(f"{PREFIX}/pose/wand"))
    assert row[1:4] == ["artrack.Pose", "json", str(intact)]

    exported = artrack("export", str(cut), "--key", "pose/wand", "--format", "tum")
    assert exported.returncode == 3
    assert len(exported.stdout.splitlines()) == intact and "is damaged" in exported.stderr


def test_record_refuses_to_overwrite_a_recording_before_joining_the_bus(recording):
    refused = artrack("record", str(recording), "--connect", "tcp/127.0.0.1:9")
    assert refused.returncode == 2 and f"{recording} exists" in refused.stderr


@pytest.mark.parametrize("command", ["record", "replay"])
def test_a_bad_key_expression_is_refused_in_one_line_before_joining_the_bus(recording, tmp_path, command: str):
    target = recording if command == "replay" else tmp_path / "new.mcap"
    refused = artrack(command, str(target), "--keys", "cam0/image", "a b//c", "--connect", "tcp/127.0.0.1:9")
    assert refused.returncode == 2, refused.stderr
    assert refused.stderr.count("\n") == 1 and "key expression 'a b//c' is not valid: it has an empty segment" \
        in refused.stderr, refused.stderr
