"""The viewer's mapping of messages to Rerun, written to a real .rrd and read back with Rerun's reader."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import rerun as rr

from protocol import (
    Blobs,
    CameraInfo,
    ErrorReport,
    FrameTransform,
    GroundTruth,
    Header,
    Image,
    Keyframes,
    Keypoints,
    MarkerDetections,
    NodeStats,
    PointCloud,
    Points3D,
    Pose,
    RigidBodies,
    RigidBody,
    StageTimings,
    StreamStats,
    TrackingState,
    Transform,
)
from services.viewer.images import RateGate
from services.viewer.recording import SinkError, ViewLog, open_recording
from services.viewer.scene import Scene, Trail, ViewOptions
from tests.viewer_contents import RrdContents

BASE_NS = 1_700_000_000_000_000_000
PERIOD_NS = 33_333_333
K = (500.0, 0.0, 32.0, 0.0, 510.0, 24.0, 0.0, 0.0, 1.0)


def header(i: int, frame: str = "cam0") -> Header:
    return Header(stamp_ns=BASE_NS + i * PERIOD_NS, frame_id=frame, seq=i)


def mono(i: int, frame: str = "cam0") -> Image:
    pixels = np.random.default_rng(i).integers(0, 256, (48, 64), dtype=np.uint8)
    return Image(header=header(i, frame), encoding="mono8", data=pixels)


def info(i: int, frame: str = "cam0", x: float = 0.0) -> CameraInfo:
    return CameraInfo(header=header(i, frame), width=64, height=48, k=K, d=(0.0,) * 5,
                      T_rig_camera=Transform(translation=(x, 0.0, 0.0)))


def pose(i: int, state: TrackingState = TrackingState.TRACKING) -> Pose:
    angle = 0.1 * i
    return Pose(header=header(i), child_frame_id="marker/7", state=state,
                transform=Transform(translation=(0.01 * i, -0.2, 1.0 + i),
                                    rotation=(0.0, math.sin(angle / 2), 0.0, math.cos(angle / 2))))


def markers(i: int, n: int) -> MarkerDetections:
    corners = np.array([[[10, 10], [20, 10], [20, 20], [10, 20]]], np.float32) + np.arange(n)[:, None, None] * 5
    return MarkerDetections(header=header(i), dictionary="DICT_4X4_50", ids=np.arange(3, 3 + n, dtype=np.int32),
                            corners=corners.astype(np.float32), quality=np.ones(n, np.float32),
                            side_m=np.full(n, 0.05, np.float32))


@pytest.fixture
def view(tmp_path):
    """``view(messages, **options)``: log ``messages`` through a Scene into a file; the file read back."""

    def run(messages, **options) -> RrdContents:
        path = tmp_path / "view.rrd"
        with ViewLog(open_recording("test", out=path), Scene(ViewOptions(**options))) as log:
            for message in messages:
                log.log(message)
        return RrdContents(path)

    return run


def test_images_keep_their_pixels_and_times_in_every_encoding(view):
    bgr = Image(header=header(1), encoding="bgr8",
                data=np.random.default_rng(1).integers(0, 256, (48, 64, 3), dtype=np.uint8))
    deep = Image(header=header(2, "cam1"), encoding="mono16",
                 data=np.random.default_rng(2).integers(0, 65536, (48, 64), dtype=np.uint16))
    contents = view([mono(0), bgr, deep])
    first, second = contents.rows("world/cam0/image", "Image:buffer")
    np.testing.assert_array_equal(first.numbers(), mono(0).data.ravel())
    np.testing.assert_array_equal(second.numbers(), bgr.data.ravel())  # BGR as it travels: Rerun swaps on display
    models = [r.values.to_pylist()[0]["color_model"] for r in contents.rows("world/cam0/image", "Image:format")]
    assert models == [rr.ColorModel.L.value, rr.ColorModel.BGR.value]
    assert first.times["stamp"] == BASE_NS and first.times["seq"] == 0
    assert second.times["stamp"] == BASE_NS + PERIOD_NS and second.times["seq"] == 1
    (wide,) = contents.rows("world/cam1/image", "Image:buffer")
    assert wide.numbers().view(np.uint16).tolist() == deep.data.ravel().tolist()


def test_jpeg_images_decode_to_nearly_the_frame(view):
    smooth = np.add.outer(np.arange(48), np.arange(64)).astype(np.uint8)
    image = Image(header=header(0), encoding="mono8", data=smooth)
    contents = view([image], jpeg_quality=90)
    assert contents.rows("world/cam0/image", "Image:buffer") == []
    (blob,) = contents.rows("world/cam0/image", "EncodedImage:blob")
    decoded = cv2.imdecode(blob.numbers().astype(np.uint8), cv2.IMREAD_GRAYSCALE)
    assert decoded.shape == (48, 64) and np.abs(decoded.astype(int) - smooth).max() <= 4


def test_rate_gate_logs_one_image_per_slot_of_frame_time(view):
    frames = [mono(i) for i in range(30)]  # 1 s at 30 fps
    assert len(view(frames, image_hz=10).rows("world/cam0/image", "Image:buffer")) == 10
    assert len(view(frames + frames[-1:]).rows("world/cam0/image", "Image:buffer")) == 30  # a repeat is held back


def test_rate_gate_counts_each_entity_apart_and_lets_a_restart_through():
    gate = RateGate(10)
    assert [gate.admit("a", t) for t in (0, 50_000_000, 100_000_000)] == [True, False, True]
    assert gate.admit("b", 50_000_000)
    assert gate.admit("a", 0)  # back in time: a replay starting over


def test_calibration_places_the_camera_and_is_logged_only_when_it_changes(view):
    contents = view([info(0), info(1), info(2, x=0.25), mono(2)])
    resolutions = contents.rows("world/cam0/image", "Pinhole:resolution")
    assert [r.numbers().tolist() for r in resolutions] == [[64.0, 48.0], [64.0, 48.0]]
    k = contents.rows("world/cam0/image", "Pinhole:image_from_camera")[0].numbers()
    np.testing.assert_allclose(k.reshape(3, 3).T, np.reshape(K, (3, 3)))  # Rerun stores matrices column-major
    placed = contents.rows("world/cam0", "Transform3D:translation")
    assert [p.numbers().tolist() for p in placed] == [[0.0, 0.0, 0.0], [0.25, 0.0, 0.0]]
    assert placed[1].times["seq"] == 2


def test_detections_are_overlays_in_the_camera_image(view):
    blobs = Blobs(header=header(0), centroids=np.array([[5.0, 6.0], [7.0, 8.0]]), areas=np.ones(2, np.float32),
                  radii=np.array([2, 3], np.float32), quality=np.ones(2, np.float32), flags=np.zeros(2, np.uint8))
    features = Keypoints(header=header(0), points=np.array([[1, 2]], np.float32), sizes=np.ones(1, np.float32),
                         angles=np.zeros(1, np.float32), responses=np.ones(1, np.float32),
                         descriptors=np.zeros((1, 32), np.uint8))
    contents = view([markers(0, 2), markers(1, 0), blobs, features])
    found, cleared = contents.rows("world/cam0/image/markers", "LineStrips2D:strips")
    outlines = found.values.to_pylist()
    assert len(outlines) == 2 and outlines[0][0] == outlines[0][4] == [10.0, 10.0]  # closed quads
    assert outlines[1][2] == [25.0, 25.0]
    assert contents.rows("world/cam0/image/markers", "LineStrips2D:labels")[0].values.to_pylist() == ["3", "4"]
    assert cleared.values.to_pylist() == []  # a frame with no markers clears the overlay
    (style,) = contents.rows("world/cam0/image/markers", "LineStrips2D:colors")
    assert style.times == {}  # colours are logged once, static
    clean = "world/cam0/image/clean_blobs"
    assert contents.rows(clean, "Points2D:positions")[0].values.to_pylist() == [[5, 6], [7, 8]]
    assert contents.rows(clean, "Points2D:radii")[0].values.to_pylist() == [2, 3]
    assert contents.rows("world/cam0/image/flagged_blobs", "Points2D:positions")[0].values.to_pylist() == []
    assert contents.rows("world/cam0/image/keypoints", "Points2D:positions")[0].values.to_pylist() == [[1, 2]]


def test_poses_are_transforms_under_their_parent_frame_with_a_bounded_trajectory(view):
    contents = view([pose(i) for i in range(6)] + [pose(6, TrackingState.LOST)], trajectory_length=4)
    moved = contents.rows("world/cam0/pose/marker/7", "Transform3D:translation")
    np.testing.assert_allclose([r.numbers() for r in moved], [pose(i).transform.translation for i in range(6)],
                               rtol=1e-6)  # Rerun keeps float32
    turned = contents.rows("world/cam0/pose/marker/7", "Transform3D:quaternion")[5].numbers()
    np.testing.assert_allclose(turned, pose(5).transform.rotation, rtol=1e-6)
    assert len(contents.rows("world/cam0/pose/marker/7", "TransformAxes3D:axis_length")) == 6
    (lost,) = contents.rows("world/cam0/pose/marker/7", "Clear:is_recursive")
    assert lost.times["seq"] == 6
    lines = contents.rows("world/cam0/trajectory/pose/marker/7", "LineStrips3D:strips")
    assert len(lines) == 6
    last_four = [pose(i).transform.translation for i in (2, 3, 4, 5)]
    np.testing.assert_allclose(lines[-1].numbers().reshape(-1, 3), last_four, rtol=1e-6)


def test_trail_keeps_the_last_positions_contiguous_across_its_buffer_end():
    trail = Trail(3)
    windows = [trail.add((float(i), 0.0, 0.0))[:, 0].tolist() for i in range(10)]
    assert windows[:3] == [[0], [0, 1], [0, 1, 2]]
    assert windows[3:] == [[i - 2, i - 1, i] for i in range(3, 10)]


def test_rigid_bodies_and_ground_truth_sit_beside_each_other(view):
    body = RigidBodies(header=header(0, "world"), bodies=(
        RigidBody(name="wand", transform=Transform(translation=(1.0, 2.0, 3.0))),
        RigidBody(name="hidden", state=TrackingState.LOST)))
    truth = [GroundTruth(header=header(i), transforms=tuple(
        FrameTransform(parent_frame="cam0", child_frame=f"marker/{m}", transform=Transform(translation=(m, 0.0, i)))
        for m in markers_seen)) for i, markers_seen in enumerate([(7, 8), (7,)])]
    contents = view([body, *truth, pose(1)])
    assert contents.rows("world/pose/body/wand", "Transform3D:translation")[0].numbers().tolist() == [1, 2, 3]
    assert len(contents.rows("world/pose/body/hidden", "Clear:is_recursive")) == 1
    known = contents.rows("world/cam0/truth/marker/7", "Transform3D:translation")
    assert [r.numbers().tolist() for r in known] == [[7, 0, 0], [7, 0, 1]]
    assert len(contents.rows("world/cam0/truth/marker/8", "Clear:is_recursive")) == 1  # left the view in frame 1
    assert {"world/cam0/pose/marker/7", "world/cam0/trajectory/truth/marker/7"} <= contents.entities


def test_point_clouds_are_points_in_their_frame_with_rgb_colours(view):
    cloud = PointCloud(header=header(0, "world"), points=np.array([[1, 2, 3], [4, 5, 6]], np.float32),
                       ids=np.array([10, 11], np.int64), colors=np.array([[255, 0, 0], [0, 0, 9]], np.uint8))
    contents = view([cloud])
    assert contents.rows("world/points", "Points3D:positions")[0].values.to_pylist() == [[1, 2, 3], [4, 5, 6]]
    colours = contents.rows("world/points", "Points3D:colors")[0].values.to_pylist()
    assert colours == [0x0000FFFF, 0x090000FF]  # RGBA: blue from BGR (255, 0, 0), red 9 from BGR (0, 0, 9)


def test_slam_keyframes_are_axes_in_the_map_frame_and_stage_times_are_scalars_per_camera(view):
    poses = np.tile(np.eye(4), (2, 1, 1))
    poses[1, :3, :3] = cv2.Rodrigues(np.array([0.0, 0.0, np.pi / 2]))[0]  # turned 90 deg about z
    poses[1, :3, 3] = (1.0, 2.0, 3.0)
    keyframes = Keyframes(header=header(5, "map"), child_frame_id="cam0", ids=np.array([0, 3]),
                          stamps_ns=np.array([BASE_NS, BASE_NS + 3 * PERIOD_NS]), poses=poses)
    timings = StageTimings(header=header(5), stages_ms={"match": 2.5, "total": 7.0})
    slam = Pose(header=header(5, "map"), child_frame_id="cam0", transform=Transform(translation=(1.0, 2.0, 3.0)))
    contents = view([keyframes, timings, slam], axis_length_m=0.5)
    arrows = "world/map/keyframes/cam0"
    (origins,) = contents.rows(arrows, "Arrows3D:origins")
    assert origins.values.to_pylist() == [[0, 0, 0]] * 3 + [[1, 2, 3]] * 3 and origins.times["seq"] == 5
    vectors = np.reshape(contents.rows(arrows, "Arrows3D:vectors")[0].numbers(), (6, 3))
    np.testing.assert_allclose(vectors[:3], 0.5 * np.eye(3))
    np.testing.assert_allclose(vectors[3:], 0.5 * np.array([[0, 1, 0], [-1, 0, 0], [0, 0, 1]]), atol=1e-7)
    assert len(contents.rows(arrows, "Arrows3D:colors")[0].values) == 6
    value = lambda entity: contents.rows(entity, "Scalars:scalars")[0].numbers().tolist()  # noqa: E731
    assert value("stats/stage_ms/cam0/match") == [2.5] and value("stats/stage_ms/cam0/total") == [7.0]
    assert contents.rows("world/map/pose/cam0", "Transform3D:translation")[0].numbers().tolist() == [1, 2, 3]
    assert "world/map/trajectory/pose/cam0" in contents.entities
    assert ("TimeSeries", "stats/stage_ms") in contents.views()


def test_node_health_is_scalars_and_text_on_the_stamp_timeline_only(view):
    stats = NodeStats(header=Header(stamp_ns=BASE_NS, seq=41), node="det", kind="detection", host="h", pid=1,
                      uptime_s=3.0, dropped=4, decode_errors=2, processing_ms_p50=1.5, processing_ms_p99=9.0,
                      latency_ms_p50=3.5, latency_ms_p99=12.0,
                      streams=(StreamStats(key="ar/rig0/cam0/image", direction="in", rate_hz=29.5),))
    report = ErrorReport(header=Header(stamp_ns=BASE_NS), node="det", kind="decode_error", detail="bad", key="k")
    contents = view([stats, report])
    value = lambda entity: contents.rows(entity, "Scalars:scalars")[0].numbers().tolist()  # noqa: E731
    assert value("stats/dropped/det") == [4] and value("stats/decode_errors/det") == [2]
    assert value("stats/processing_ms/det/p50") == [1.5] and value("stats/processing_ms/det/p99") == [9.0]
    assert value("stats/latency_ms/det/p50") == [3.5] and value("stats/latency_ms/det/p99") == [12.0]
    assert value("stats/rate_hz/det/in/ar/rig0/cam0/image") == [29.5]
    row = contents.rows("stats/dropped/det", "Scalars:scalars")[0]
    assert row.times["stamp"] == BASE_NS and "seq" not in row.times
    text = contents.rows("logs/det", "TextLog:text")[0].values.to_pylist()
    assert text == ["decode_error on k: bad (1 so far)"]


def test_blueprint_has_a_2d_view_per_camera_and_the_world_has_its_axes(view):
    contents = view([mono(0), info(0, "cam1")], world_axes="RFU")
    views = contents.views()
    assert ("2D", "world/cam0/image") in views and ("2D", "world/cam1/image") in views
    assert ("3D", "world") in views and ("TimeSeries", "stats/rate_hz") in views
    (axes,) = contents.rows("world", "ViewCoordinates:xyz")
    assert axes.times == {} and axes.numbers().tolist() == [3, 5, 1]  # Right, Forward, Up


def test_options_and_sinks_refuse_what_cannot_work(tmp_path):
    with pytest.raises(ValueError, match="view coordinates"):
        ViewOptions(world_axes="XYZ")
    with pytest.raises(SinkError, match="not a folder"):
        open_recording("test", out=tmp_path / "missing" / "view.rrd")
    with pytest.raises(SinkError, match="nothing to write to"):
        open_recording("test")


def test_blobs_and_points_are_drawn_apart_by_flag_and_by_body(view):
    blobs = Blobs(header=header(0), centroids=np.array([[5.0, 6.0], [7.0, 8.0]]), areas=np.ones(2, np.float32),
                  radii=np.array([2, 3], np.float32), quality=np.ones(2, np.float32),
                  flags=np.array([0, 1], np.uint8))
    points = Points3D(header=header(0, "world"), bodies=("wand",), points=np.array([[1.0, 2, 3], [4, 5, 6]]),
                      residual_px=np.zeros(2, np.float32), views=np.full(2, 2, np.uint8),
                      covariances=np.zeros((2, 3, 3)), body=np.array([-1, 0], np.int32))
    contents = view([blobs, points])
    assert contents.rows("world/cam0/image/clean_blobs", "Points2D:positions")[0].values.to_pylist() == [[5, 6]]
    assert contents.rows("world/cam0/image/flagged_blobs", "Points2D:positions")[0].values.to_pylist() == [[7, 8]]
    labelled = contents.rows("world/points/labelled", "Points3D:positions")[0].values.to_pylist()
    assert labelled == [[4, 5, 6]]
    assert contents.rows("world/points/labelled", "Points3D:labels")[0].values.to_pylist() == ["wand"]
    assert contents.rows("world/points/unlabelled", "Points3D:positions")[0].values.to_pylist() == [[1, 2, 3]]
