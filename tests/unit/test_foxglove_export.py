"""``artrack export --format foxglove``: a shipped recording rewritten with Foxglove's schemas, read back with
mcap's reader and the schemas' own protobuf descriptors, and opened with Rerun's MCAP loader."""

from __future__ import annotations

import numpy as np
import pytest
import rerun as rr
from mcap.reader import make_reader

from protocol import (
    CameraInfo,
    GroundTruth,
    Header,
    Image,
    MarkerDetections,
    PointCloud,
    Points3D,
    Pose,
    Trajectory,
    Transform,
    decode,
    encode,
)
from services.cli import main
from services.recorder.reading import EXIT_DAMAGED, Scan
from services.recorder.writing import RecordingWriter
from services.viewer.foxglove_export import export_foxglove
from tests.data import REPO_ROOT
from tests.foxglove_decoding import decoded
from tests.viewer_contents import RrdContents

SHIPPED = REPO_ROOT / "recordings" / "ir_rig.mcap"
SCHEMAS = {"/cam0/image": "foxglove.RawImage", "/cam1/image": "foxglove.RawImage",
           "/cam0/camera_info": "foxglove.CameraCalibration", "/cam1/camera_info": "foxglove.CameraCalibration",
           "/cam0/truth": "foxglove.FrameTransforms", "/cam1/truth": "foxglove.FrameTransforms",
           "/tf": "foxglove.FrameTransforms"}


def source_messages(path, key_suffix: str) -> list:
    """The artrack messages recorded on the key ending in ``key_suffix``, in file order."""
    return [decode(r.message.data) for r in Scan(path).messages() if r.channel.topic.endswith(key_suffix)]


def read_back(path) -> tuple[object, dict[str, list]]:
    """The summary and ``{topic: [(schema name, log time, decoded message)]}`` of an exported file."""
    found: dict[str, list] = {}
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            assert channel.message_encoding == "protobuf" and schema.encoding == "protobuf"
            found.setdefault(channel.topic, []).append(
                (schema.name, message.log_time, decoded(schema.name, schema.data, message.data)))
    return summary, found


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    out = tmp_path_factory.mktemp("foxglove") / "ir_rig.foxglove.mcap"
    assert main(["export", str(SHIPPED), "--format", "foxglove", "-o", str(out)]) == 0
    return out


def test_every_channel_has_its_foxglove_schema_and_the_file_is_chunked_sorted_and_summarised(exported):
    summary, found = read_back(exported)
    assert {topic: {name for name, _, _ in rows} for topic, rows in found.items()} == {
        topic: {name} for topic, name in SCHEMAS.items()}
    assert summary.statistics.chunk_count >= 1 and summary.chunk_indexes
    assert summary.statistics.message_count == sum(len(rows) for rows in found.values()) == 7 * 60 + 60
    with open(exported, "rb") as f:
        log_times = [m.log_time for _, _, m in make_reader(f).iter_messages(log_time_order=False)]
    assert log_times == sorted(log_times)


def test_decoded_values_match_the_recording(exported):
    _, found = read_back(exported)
    image = source_messages(SHIPPED, "cam1/image")[5]
    raw = found["/cam1/image"][5][2]
    assert (raw.width, raw.height, raw.frame_id) == (image.width, image.height, "cam1")
    assert raw.timestamp.seconds * 10**9 + raw.timestamp.nanos == image.header.stamp_ns
    np.testing.assert_array_equal(np.frombuffer(raw.data, np.uint8).reshape(image.data.shape), image.data)
    info: CameraInfo = source_messages(SHIPPED, "cam1/camera_info")[0]
    np.testing.assert_array_equal(found["/cam1/camera_info"][0][2].K, info.k)
    placements = {(e.parent_frame_id, e.child_frame_id): e for _, _, tf in found["/tf"] for e in tf.transforms}
    cam1 = placements[("rig", "cam1")]
    assert [cam1.translation.x, cam1.translation.y, cam1.translation.z] == pytest.approx(
        info.T_rig_camera.translation)
    truth: GroundTruth = source_messages(SHIPPED, "cam0/truth")[3]
    facts = found["/cam0/truth"][3][2].transforms
    assert [(f.parent_frame_id, f.child_frame_id) for f in facts] == [
        (t.parent_frame, "truth/" + t.child_frame) for t in truth.transforms]
    assert [facts[0].rotation.x, facts[0].rotation.y, facts[0].rotation.z, facts[0].rotation.w] == pytest.approx(
        truth.transforms[0].transform.rotation)


def loaded_by_rerun(path, out) -> RrdContents:
    """``path`` read by Rerun's own MCAP loader into the .rrd ``out``, and read back."""
    recording = rr.RecordingStream("artrack", recording_id=out.stem)
    recording.set_sinks(rr.FileSink(str(out)))
    rr.log_file_from_path(path, recording=recording)
    recording.flush()
    recording.disconnect()
    return RrdContents(out)


def test_rerun_loads_the_export_as_images_pinholes_and_transforms(exported, tmp_path):
    contents = loaded_by_rerun(exported, tmp_path / "loaded.rrd")
    images = contents.rows("cam0/image", "Image:buffer")
    assert len(images) == 60
    first = source_messages(SHIPPED, "cam0/image")[0]
    np.testing.assert_array_equal(images[0].numbers(), first.data.ravel())
    assert len(contents.rows("cam1/camera_info", "Pinhole:image_from_camera")) == 60
    assert len(contents.rows("tf", "Transform3D:translation")) == 60 * 2 * 2  # world -> rig, rig -> camera


def test_poses_points_and_detections_of_a_tracked_run_are_exported(tmp_path):
    source = tmp_path / "tracked.mcap"
    writer = RecordingWriter(source, metadata={"namespace": "ar", "rig": "lab"})
    for i in range(3):
        header = Header(stamp_ns=1_700_000_000_000_000_000 + i, frame_id="cam0", seq=i)
        world = Header(stamp_ns=header.stamp_ns, frame_id="world", seq=i)
        writer.write("ar/lab/pose/marker-3", encode(Pose(header=header, child_frame_id="marker/3",
                                                         transform=Transform(translation=(0.0, 0.0, 1.0 + i)))),
                     10_000 + 3 * i)
        writer.write("ar/lab/cam0/markers", encode(MarkerDetections(
            header=header, dictionary="DICT_4X4_50", ids=np.array([3], np.int32),
            corners=np.full((1, 4, 2), 5.0, np.float32), quality=np.ones(1, np.float32),
            side_m=np.full(1, 0.05, np.float32))), 10_001 + 3 * i)
        writer.write("ar/lab/points", encode(Points3D(
            header=world, points=np.zeros((2, 3)), residual_px=np.zeros(2, np.float32), views=np.full(2, 2, np.uint8),
            covariances=np.zeros((2, 3, 3)), body=np.full(2, -1, np.int32))), 10_002 + 3 * i)
    writer.write("ar/lab/junk", b"not an artrack message", 20_000)
    writer.close()
    done = export_foxglove(source, tmp_path / "tracked.foxglove.mcap")
    assert (done.read, done.undecodable, done.damage) == (10, 1, None)
    _, found = read_back(tmp_path / "tracked.foxglove.mcap")
    assert {topic: (rows[0][0], len(rows)) for topic, rows in found.items()} == {
        "/pose/cam0/marker/3": ("foxglove.PoseInFrame", 3), "/tf": ("foxglove.FrameTransforms", 3),
        "/cam0/markers": ("foxglove.ImageAnnotations", 3), "/cam0/marker_outlines": ("foxglove.SceneUpdate", 3),
        "/world/points": ("foxglove.PointCloud", 3), "/world/spheres": ("foxglove.SceneUpdate", 3)}
    assert found["/pose/cam0/marker/3"][2][2].pose.position.z == 3.0
    contents = loaded_by_rerun(tmp_path / "tracked.foxglove.mcap", tmp_path / "tracked.rrd")
    moved = contents.rows("pose/cam0/marker/3", "InstancePoses3D:translations")
    assert [row.numbers().tolist() for row in moved] == [[0.0, 0.0, 1.0], [0.0, 0.0, 2.0], [0.0, 0.0, 3.0]]
    assert len(contents.rows("world/points", "Points3D:positions")) == 3


def test_a_slam_run_exports_its_map_points_as_a_cloud_and_its_camera_in_the_one_tree(tmp_path):
    source = tmp_path / "slam.mcap"
    writer = RecordingWriter(source, metadata={"namespace": "ar", "rig": "lab"})
    for i in range(3):
        header = Header(stamp_ns=1_700_000_000_000_000_000 + i, frame_id="cam0", seq=i)
        in_map = header.model_copy(update={"frame_id": "map"})
        writer.write("ar/lab/cam0/camera_info", encode(CameraInfo(
            header=header, width=64, height=48, k=(50.0, 0, 32, 0, 50.0, 24, 0, 0, 1),
            T_rig_camera=Transform(translation=(0.0, 0.1, 0.0)))), 10_000 + 3 * i)
        writer.write("ar/lab/pose/slam/cam0", encode(Pose(
            header=in_map, child_frame_id="cam0", transform=Transform(translation=(0.2 * i, 0.0, 0.0)))),
            10_001 + 3 * i)
        writer.write("ar/lab/cam0/map", encode(PointCloud(
            header=in_map, ids=np.arange(4, dtype=np.int64), points=np.full((4, 3), float(i), np.float32),
            colors=np.zeros((0, 3), np.uint8))), 10_002 + 3 * i)
    writer.write("ar/lab/cam0/trajectory", encode(Trajectory(
        header=in_map, child_frame_id="cam0", stamps_ns=np.arange(3, dtype=np.int64),
        seqs=np.arange(3, dtype=np.int64), poses=np.stack([np.eye(4)] * 3))), 10_010)
    writer.close()
    export_foxglove(source, tmp_path / "slam.foxglove.mcap")
    _, found = read_back(tmp_path / "slam.foxglove.mcap")
    assert {topic: rows[0][0] for topic, rows in found.items()} == {
        "/cam0/camera_info": "foxglove.CameraCalibration", "/tf": "foxglove.FrameTransforms",
        "/pose/map/cam0": "foxglove.PoseInFrame", "/map/map": "foxglove.PointCloud",
        "/map/trajectory/cam0": "foxglove.PosesInFrame"}
    [(_, _, final)] = found["/map/trajectory/cam0"]
    assert final.frame_id == "map" and len(final.poses) == 3
    cloud = found["/map/map"][2][2]
    assert cloud.frame_id == "map" and cloud.point_stride == 12
    np.testing.assert_array_equal(np.frombuffer(cloud.data, "<f4"), np.full(12, 2.0))
    parents: dict[str, set[str]] = {}
    for _, _, tf in found["/tf"]:
        for edge in tf.transforms:
            parents.setdefault(edge.child_frame_id, set()).add(edge.parent_frame_id)
    assert parents == {"rig": {"world"}, "cam0": {"rig"}, "map": {"cam0"}}
    last = [e for _, _, tf in found["/tf"] for e in tf.transforms if e.child_frame_id == "map"][-1]
    assert [last.translation.x, last.translation.y, last.translation.z] == pytest.approx([-0.4, 0.0, 0.0])
    contents = loaded_by_rerun(tmp_path / "slam.foxglove.mcap", tmp_path / "slam.rrd")
    assert len(contents.rows("map/map", "Points3D:positions")) == 3


def test_a_damaged_recording_exports_its_intact_part_with_one_warning_and_exit_3(tmp_path, capsys):
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(SHIPPED.read_bytes()[: SHIPPED.stat().st_size * 6 // 10])
    out = tmp_path / "cut.foxglove.mcap"
    assert main(["export", str(cut), "--format", "foxglove", "-o", str(out)]) == EXIT_DAMAGED
    warnings = [line for line in capsys.readouterr().err.splitlines() if " WARNING " in line]
    assert len(warnings) == 1 and "is damaged" in warnings[0]
    _, found = read_back(out)
    intact = len(source_messages(cut, "cam0/image"))
    assert 0 < intact < 60 and len(found["/cam0/image"]) == intact


def test_an_existing_output_is_refused_unless_forced_and_other_formats_still_need_a_key(exported, tmp_path, capsys):
    before = exported.stat().st_mtime_ns
    assert main(["export", str(SHIPPED), "--format", "foxglove", "-o", str(exported)]) == 2
    assert exported.stat().st_mtime_ns == before and "give --force" in capsys.readouterr().err
    assert main(["export", str(SHIPPED), "--format", "foxglove", "-o", str(exported), "--force"]) == 0
    assert main(["export", str(SHIPPED), "--format", "foxglove", "--key", "cam0/image",
                 "-o", str(tmp_path / "x.mcap")]) == 2
    assert main(["export", str(SHIPPED), "--format", "tum"]) == 2
    assert not (tmp_path / "x.mcap").exists()


def test_images_can_be_exported_as_jpeg(tmp_path):
    out = tmp_path / "small.mcap"
    assert main(["export", str(SHIPPED), "--format", "foxglove", "--compressed", "-o", str(out)]) == 0
    _, found = read_back(out)
    assert {name for name, _, _ in found["/cam0/image"]} == {"foxglove.CompressedImage"}
    assert found["/cam0/image"][0][2].format == "jpeg"
    assert isinstance(source_messages(SHIPPED, "cam0/image")[0], Image)


def test_messages_recorded_out_of_log_time_order_are_written_in_order(tmp_path):
    source = tmp_path / "late.mcap"
    writer = RecordingWriter(source, metadata={"namespace": "ar", "rig": "lab"})
    arrivals = [3_000_000_000, 1_500_000_000, 2_000_000_000]  # within the reorder window of each other
    for i, arrived in enumerate(arrivals):
        posed = Pose(header=Header(stamp_ns=arrived, frame_id="cam0", seq=i), child_frame_id="marker/3")
        writer.write("ar/lab/pose/marker-3", encode(posed), arrived)
    writer.close()
    export_foxglove(source, tmp_path / "late.foxglove.mcap")
    _, found = read_back(tmp_path / "late.foxglove.mcap")
    assert [log_ns for _, log_ns, _ in found["/pose/cam0/marker/3"]] == sorted(arrivals)
    assert [m.timestamp.seconds for _, _, m in found["/pose/cam0/marker/3"]] == [1, 2, 3]
