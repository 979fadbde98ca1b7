"""``export`` (TUM, CSV, JSON lines) and ``info`` on recordings written for the test."""

from __future__ import annotations

import csv
import io
import json
import math
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from protocol import Header, Image, Pose, Trajectory, encode, to_json
from protocol.codec import sample_record
from protocol.spatial import Transform
from protocol.system import ErrorReport
from protocol.tracking_state import TrackingState
from services.geometry.se3 import from_quaternion_translation, make_transform
from services.recorder.export import Export, ExportError, flatten, tum_line
from services.recorder.info import format_info, summarise
from services.recorder.writing import RecordingWriter

MS = 1_000_000


def pose(i: int) -> Pose:
    return Pose(header=Header(stamp_ns=1_600_000_000_000_000_007 + i * 50 * MS, frame_id="cam0", seq=i),
                child_frame_id="marker/3" if i % 2 else "marker/4",
                transform=Transform(translation=(0.1 + i, 1e-9 * i, -3.25),
                                    rotation=(0.0, 0.0, math.sin(i), math.cos(i))),
                covariance=tuple(float(k) for k in range(36)) if i == 1 else None)


@pytest.fixture
def recording(tmp_path) -> Path:
    """10 poses and a raw payload on ``pose/m`` and 5 images on ``cam0/image``, rig ``ar/r``; 20 ms apart."""
    path = tmp_path / "r.mcap"
    writer = RecordingWriter(path, metadata={"namespace": "ar", "rig": "r"})
    t = 0
    for i in range(10):
        writer.write("ar/r/pose/m", encode(pose(i)), t := t + 20 * MS)
        if i % 2 == 0:
            image = Image(header=Header(stamp_ns=i), encoding="mono8", data=np.full((4, 5), i, np.uint8))
            writer.write("ar/r/cam0/image", encode(image), t := t + 20 * MS)
    writer.write("ar/r/pose/m", b"\x00 not a message", t + 20 * MS)
    writer.close()
    return path


def test_tum_lines_are_exact():
    transform = Transform(translation=(0.1, -1 / 3, 2.0), rotation=(0.0, 0.0, 0.6, 0.8))
    line = tum_line(1_700_000_000_000_000_042, transform)
    assert line == "1700000000.000000042 0.1 -0.3333333333333333 2.0 0.0 0.0 0.6 0.8"
    assert tum_line(5, transform).startswith("0.000000005 ")


def test_a_trajectory_key_exports_the_rows_of_its_last_message(tmp_path):
    path = tmp_path / "trajectory.mcap"
    writer = RecordingWriter(path, metadata={"namespace": "ar", "rig": "r"})
    poses = np.stack([make_transform(Rotation.from_rotvec([0.0, 0.1 * i, 0.0]).as_matrix(), [0.5 * i, 0.0, 1.0])
                      for i in range(3)])
    for count in (2, 3):  # a map's trajectory, then the map's final one
        writer.write("ar/r/cam0/trajectory", encode(Trajectory(
            header=Header(stamp_ns=count, frame_id="map", seq=9), child_frame_id="cam0",
            stamps_ns=np.arange(count, dtype=np.int64) * 100 * MS + 7, seqs=np.arange(count, dtype=np.int64) + 4,
            poses=poses[:count])), count * MS)
    writer.close()
    rows = list(Export(path, "cam0/trajectory", "tum").transforms())
    assert [(header.stamp_ns, header.seq, header.frame_id) for header, _ in rows] == [
        (7, 4, "map"), (100 * MS + 7, 5, "map"), (200 * MS + 7, 6, "map")]
    for (_, transform), T in zip(rows, poses, strict=True):
        assert from_quaternion_translation(np.array(transform.rotation), np.array(transform.translation)) == \
            pytest.approx(T, abs=1e-12)


def test_flatten_names_nested_fields_by_path():
    assert flatten({"a": {"b": [1, {"c": None}]}, "d": "x", "e": []}) == {"a.b.0": 1, "a.b.1.c": None, "d": "x"}


def test_tum_export_leaves_out_poses_without_an_estimate(tmp_path):
    path = tmp_path / "lost.mcap"
    writer = RecordingWriter(path, metadata={"namespace": "ar", "rig": "r"})
    for i in range(4):
        lost = pose(i).model_copy(update={"state": TrackingState.LOST, "transform": Transform()}) if i == 2 else pose(i)
        writer.write("ar/r/pose/m", encode(lost), (i + 1) * MS)
    writer.close()
    assert list(Export(path, "pose/m", "tum").lines()) == [
        tum_line(pose(i).header.stamp_ns, pose(i).transform) for i in (0, 1, 3)]


FRESH = (TrackingState.TRACKING, TrackingState.RECOGNISED)


def _middle_pose_in(tmp_path, state: TrackingState) -> list[str]:
    """TUM lines of three poses whose middle one has ``state``."""
    path = tmp_path / "states.mcap"
    writer = RecordingWriter(path, metadata={"namespace": "ar", "rig": "r"})
    for i in range(3):
        writer.write("ar/r/pose/m", encode(pose(i).model_copy(update={"state": state}) if i == 1 else pose(i)),
                     (i + 1) * MS)
    writer.close()
    return list(Export(path, "pose/m", "tum").lines())


@pytest.mark.parametrize("state", [s for s in TrackingState if s not in FRESH])
def test_tum_export_writes_fresh_estimates_only(tmp_path, state):
    assert _middle_pose_in(tmp_path, state) == [tum_line(pose(i).header.stamp_ns, pose(i).transform) for i in (0, 2)]


def test_tum_export_keeps_a_pose_found_from_scratch(tmp_path):
    assert _middle_pose_in(tmp_path, TrackingState.RECOGNISED) == [
        tum_line(pose(i).header.stamp_ns, pose(i).transform) for i in (0, 1, 2)]


def test_tum_export_of_poses_with_and_without_a_child_filter(recording):
    every = Export(recording, "pose/m", "tum")
    assert list(every.lines()) == [tum_line(pose(i).header.stamp_ns, pose(i).transform) for i in range(10)]
    assert (every.rows, every.skipped, every.damage) == (10, 1, None)  # the raw payload is skipped, counted
    odd = Export(recording, "ar/r/pose/m", "tum", child="marker/3")
    assert list(odd.lines()) == [tum_line(pose(i).header.stamp_ns, pose(i).transform) for i in range(1, 10, 2)]


def test_jsonl_lines_look_like_echo_output(recording):
    lines = [json.loads(line) for line in Export(recording, "cam0/image", "jsonl").lines()]
    assert [line["key"] for line in lines] == ["ar/r/cam0/image"] * 5
    assert lines[0]["data"] == {"dtype": "uint8", "shape": [4, 5]}  # over 16 elements: summarised
    full = [json.loads(line) for line in Export(recording, "cam0/image", "jsonl", full=True).lines()]
    assert full[1]["data"] == [[2] * 5] * 4 and full[1]["received_ns"] > full[0]["received_ns"]
    assert {k: v for k, v in full[1].items() if k not in ("key", "received_ns")} == to_json(
        Image(header=Header(stamp_ns=2), encoding="mono8", data=np.full((4, 5), 2, np.uint8)))


def test_jsonl_keeps_the_recorded_key_and_an_error_reports_own_key(tmp_path):
    path = tmp_path / "errors.mcap"
    writer = RecordingWriter(path, metadata={"namespace": "ar", "rig": "r"})
    report = ErrorReport(header=Header(stamp_ns=3), node="marker", kind="no_calibration", detail="none",
                         key="ar/r/cam0/camera_info")
    writer.write("ar/r/node/marker/errors", encode(report), 7)
    writer.close()
    [line] = [json.loads(line) for line in Export(path, "node/marker/errors", "jsonl").lines()]
    assert (line["key"], line["message_key"], line["received_ns"]) == ("ar/r/node/marker/errors",
                                                                       "ar/r/cam0/camera_info", 7)
    assert sample_record("k", 7, report) == {"key": "k", "received_ns": 7, "schema": "artrack.ErrorReport",
                                             "version": 1, "message_key": "ar/r/cam0/camera_info",
                                             **{k: v for k, v in to_json(report).items() if k != "key"}}


def test_csv_columns_are_the_union_of_every_message_fields(recording):
    text = "\n".join(Export(recording, "pose/m", "csv").lines())
    rows = list(csv.DictReader(io.StringIO(text)))
    assert len(rows) == 10
    assert "covariance.35" in rows[0] and rows[0]["covariance.35"] == "" and rows[1]["covariance.35"] == "35.0"
    assert [float(r["transform.translation.0"]) for r in rows] == [pose(i).transform.translation[0] for i in range(10)]
    assert rows[3]["child_frame_id"] == "marker/3" and rows[3]["header.stamp_ns"] == str(pose(3).header.stamp_ns)


def test_exports_that_do_not_fit_are_refused(recording):
    with pytest.raises(ExportError, match=r"no key 'pose/x' in .* \(keys: ar/r/cam0/image, ar/r/pose/m\)"):
        list(Export(recording, "pose/x", "csv").lines())
    with pytest.raises(ExportError, match="tum needs Pose, GroundTruth or Trajectory messages; cam0/image carries "
                                          "artrack.Image"):
        list(Export(recording, "cam0/image", "tum").lines())
    with pytest.raises(ExportError, match="unknown format 'xml'"):
        Export(recording, "pose/m", "xml")


def test_info_counts_channels_rates_and_sizes(recording):
    info = summarise(recording)
    assert info.damage is None and info.indexed and info.messages == 16
    by_key = {(c.key, c.schema): c for c in info.channels}
    poses = by_key["ar/r/pose/m", "artrack.Pose"]
    assert poses.messages == 10 and poses.encoding == "json"
    assert poses.rate_hz == pytest.approx(9 / ((poses.last_ns - poses.first_ns) / 1e9))
    assert by_key["ar/r/pose/m", ""].messages == 1 and by_key["ar/r/pose/m", ""].rate_hz is None
    assert by_key["ar/r/cam0/image", "artrack.Image"].payload_bytes == 5 * len(
        encode(Image(header=Header(stamp_ns=0), encoding="mono8", data=np.zeros((4, 5), np.uint8))))
    assert info.duration_s == pytest.approx(0.30)  # 20 ms to 320 ms
    assert json.loads(json.dumps(info.to_dict()))["channels"][0]["rate_hz"] is not None
    text = format_info(info)
    assert "status     intact" in text and "recording  ar/r" in text and "(raw)" in text


def test_info_of_a_cut_file_describes_its_intact_part(recording, tmp_path):
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(recording.read_bytes()[:600])
    info = summarise(cut)
    assert info.damage is not None and not info.indexed and info.messages < 16
    assert f"DAMAGED: stopped at byte {info.damage.offset} of 600" in format_info(info)
