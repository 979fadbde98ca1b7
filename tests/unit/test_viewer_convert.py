"""Recordings written by the recorder's own writer, converted to .rrd in-process and read back."""

from __future__ import annotations

import numpy as np
import pytest

from protocol import CameraInfo, Header, Image, MarkerDetections, NodeStats, Pose, Transform, encode
from services.recorder.reading import NotMcap
from services.recorder.writing import RecordingWriter
from services.viewer.convert import convert
from services.viewer.scene import ViewOptions
from tests.viewer_contents import RrdContents

PREFIX = "ar/lab"
FRAMES = 20
BASE_NS = 1_700_000_000_000_000_000
PERIOD_NS = 33_333_333


def frame(i: int) -> tuple[Image, CameraInfo, Pose, MarkerDetections]:
    header = Header(stamp_ns=BASE_NS + i * PERIOD_NS, frame_id="cam0", seq=i)
    image = Image(header=header, encoding="bgr8",
                  data=np.random.default_rng(i).integers(0, 256, (48, 64, 3), dtype=np.uint8))
    info = CameraInfo(header=header, width=64, height=48, k=(50.0, 0.0, 32.0, 0.0, 50.0, 24.0, 0.0, 0.0, 1.0))
    pose = Pose(header=header, child_frame_id="marker/3", transform=Transform(translation=(0.0, 0.1 * i, 1.0)))
    found = MarkerDetections(header=header, dictionary="DICT_4X4_50", ids=np.array([3], np.int32),
                             corners=np.full((1, 4, 2), float(i), np.float32), quality=np.ones(1, np.float32),
                             side_m=np.full(1, 0.05, np.float32))
    return image, info, pose, found


@pytest.fixture
def recording(tmp_path):
    """FRAMES instants of cam0 (image, calibration, marker pose, detections), node stats, one raw payload."""
    path = tmp_path / "session.mcap"
    writer = RecordingWriter(path, metadata={"namespace": "ar", "rig": "lab"})
    for i in range(FRAMES):
        image, info, pose, found = frame(i)
        arrived = 2_000_000_000 + i * PERIOD_NS
        writer.write(f"{PREFIX}/cam0/image", encode(image), arrived)
        writer.write(f"{PREFIX}/cam0/camera_info", encode(info), arrived + 1)
        writer.write(f"{PREFIX}/cam0/markers", encode(found), arrived + 2)
        writer.write(f"{PREFIX}/pose/marker-3", encode(pose), arrived + 3)
        if i % 10 == 9:
            writer.flush()
    stats = NodeStats(header=Header(stamp_ns=BASE_NS), node="cam", kind="capture", host="h", pid=1, uptime_s=1.0)
    writer.write(f"{PREFIX}/node/cam/stats", encode(stats), 3_000_000_000)
    writer.write(f"{PREFIX}/junk", b"not an artrack message", 3_000_000_001)
    writer.close()
    return path


def test_a_recording_converts_to_the_entities_the_live_viewer_logs(recording, tmp_path):
    out = tmp_path / "session.rrd"
    done = convert(recording, out, ViewOptions())
    assert (done.messages, done.undecodable, done.damage) == (4 * FRAMES + 2, 1, None)
    contents = RrdContents(out)
    images = contents.rows("world/cam0/image", "Image:buffer")
    assert len(images) == FRAMES  # offline: every frame unless limited
    np.testing.assert_array_equal(images[7].numbers(), frame(7)[0].data.ravel())
    assert [r.times["seq"] for r in images] == list(range(FRAMES))
    assert len(contents.rows("world/cam0/image", "Pinhole:resolution")) == 1
    moved = contents.rows("world/cam0/pose/marker/3", "Transform3D:translation")
    np.testing.assert_allclose([r.numbers() for r in moved], [frame(i)[2].transform.translation for i in range(FRAMES)],
                               rtol=1e-6)
    assert len(contents.rows("world/cam0/image/markers", "LineStrips2D:strips")) == FRAMES
    assert len(contents.rows("stats/dropped/cam", "Scalars:scalars")) == 1
    assert ("2D", "world/cam0/image") in contents.views()


def test_options_limit_and_compress_images(recording, tmp_path):
    out = tmp_path / "small.rrd"
    convert(recording, out, ViewOptions(image_hz=10, jpeg_quality=75))
    contents = RrdContents(out)
    assert contents.rows("world/cam0/image", "Image:buffer") == []
    assert len(contents.rows("world/cam0/image", "EncodedImage:blob")) == 7  # 20 frames of 1/30 s span 7 slots


def test_a_damaged_recording_converts_up_to_its_damage(recording, tmp_path):
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(recording.read_bytes()[: recording.stat().st_size * 2 // 3])
    out = tmp_path / "cut.rrd"
    done = convert(cut, out, ViewOptions())
    assert done.damage is not None and 0 < done.messages < 4 * FRAMES
    assert 0 < len(RrdContents(out).rows("world/cam0/image", "Image:buffer")) < FRAMES


def test_a_file_that_is_not_mcap_is_refused_before_anything_is_written(tmp_path):
    source, out = tmp_path / "notes.mcap", tmp_path / "notes.rrd"
    source.write_text("hello")
    with pytest.raises(NotMcap):
        convert(source, out, ViewOptions())
    assert not out.exists()
