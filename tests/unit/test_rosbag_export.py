"""``export --format rosbag2``: artrack messages as ROS 2 messages, and a shipped recording as a bag read back
with ``rosbags`` (its Reader and the typestore's CDR deserializer, independent of the writer)."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.writer import Writer
from rosbags.rosbag2 import Reader

from protocol.codec import decode, encode
from protocol.maps import PointCloud
from protocol.message import Header
from protocol.mocap import Points3D
from protocol.poses import Pose, RigidBodies, RigidBody
from protocol.sensors import CameraInfo, Image
from protocol.spatial import FrameTransform, StaticTransforms, Transform
from protocol.tracking_state import TrackingState
from services.cli import main
from services.recorder.reading import EXIT_DAMAGED, Scan
from services.recorder.rosbag import (
    TYPESTORE,
    body_edges,
    camera_info_message,
    export_rosbag,
    image_message,
    map_message,
    points_message,
    pose_message,
    ros_topic,
    tf_edges,
)
from tests.integration.support import ROOT

MARKERS = ROOT / "recordings" / "markers.mcap"
HEADER = Header(stamp_ns=1_700_000_123_456_789_012, frame_id="cam0", seq=4)
TURN = Transform(translation=(0.1, -0.2, 1.5), rotation=(0.0, 0.6, 0.0, 0.8))


def round_trip(message, msgtype):
    """The message through CDR and back, as a ROS node would receive it."""
    return TYPESTORE.deserialize_cdr(TYPESTORE.serialize_cdr(message, msgtype), msgtype)


def test_stamps_are_seconds_and_nanoseconds_and_frames_keep_their_names():
    ros = round_trip(pose_message(Pose(header=HEADER, child_frame_id="marker/3", transform=TURN)),
                     "geometry_msgs/msg/PoseStamped")
    assert (ros.header.stamp.sec, ros.header.stamp.nanosec) == (1_700_000_123, 456_789_012)
    assert ros.header.frame_id == "cam0"
    assert (ros.pose.position.x, ros.pose.position.y, ros.pose.position.z) == TURN.translation
    orientation = ros.pose.orientation
    assert (orientation.x, orientation.y, orientation.z, orientation.w) == TURN.rotation


@pytest.mark.parametrize(("encoding", "data"), [
    ("mono8", np.arange(12, dtype=np.uint8).reshape(3, 4)),
    ("mono16", (np.arange(12, dtype=np.uint16) * 5000).reshape(3, 4)),
    ("bgr8", np.arange(36, dtype=np.uint8).reshape(3, 4, 3)),
    ("bgra8", np.arange(48, dtype=np.uint8).reshape(3, 4, 4)),
])
def test_images_keep_their_pixels_row_by_row(encoding, data):
    ros = round_trip(image_message(Image(header=HEADER, encoding=encoding, data=data)), "sensor_msgs/msg/Image")
    assert (ros.encoding, ros.height, ros.width, ros.is_bigendian) == (encoding, 3, 4, 0)
    assert ros.step == 4 * data.itemsize * (data.shape[2] if data.ndim == 3 else 1)
    assert bytes(ros.data) == data.astype(data.dtype.newbyteorder("<")).tobytes()


def test_camera_info_carries_k_d_r_and_a_projection_made_from_k():
    k = (500.0, 0.0, 319.5, 0.0, 510.0, 239.5, 0.0, 0.0, 1.0)
    info = CameraInfo(header=HEADER, width=640, height=480, d=(0.1, -0.2, 0.001, 0.002, 0.05), k=k)
    ros = round_trip(camera_info_message(info), "sensor_msgs/msg/CameraInfo")
    assert (ros.width, ros.height, ros.distortion_model) == (640, 480, "plumb_bob")
    assert ros.k.tolist() == list(k) and ros.d.tolist() == list(info.d) and ros.r.tolist() == list(info.r)
    assert ros.p.reshape(3, 4).tolist() == np.hstack([np.reshape(k, (3, 3)), np.zeros((3, 1))]).tolist()


def test_static_transforms_become_tf_static_edges():
    edges = StaticTransforms(header=HEADER.model_copy(update={"frame_id": "rig"}), transforms=(
        FrameTransform(parent_frame="rig", child_frame="cam0", transform=Transform()),
        FrameTransform(parent_frame="rig", child_frame="cam1", transform=TURN)))
    ros = round_trip(tf_edges(edges.header.stamp_ns, edges.transforms), "tf2_msgs/msg/TFMessage")
    assert [(t.header.frame_id, t.child_frame_id) for t in ros.transforms] == [("rig", "cam0"), ("rig", "cam1")]
    moved = ros.transforms[1].transform
    assert (moved.translation.x, moved.translation.y, moved.translation.z) == TURN.translation
    assert (moved.rotation.x, moved.rotation.y, moved.rotation.z, moved.rotation.w) == TURN.rotation


def test_estimated_rigid_bodies_become_world_to_body_transforms():
    bodies = RigidBodies(header=HEADER.model_copy(update={"frame_id": "world"}), bodies=(
        RigidBody(name="wand", transform=TURN), RigidBody(name="tool", state=TrackingState.LOST)))
    ros = round_trip(tf_edges(bodies.header.stamp_ns, body_edges(bodies)), "tf2_msgs/msg/TFMessage")
    assert [(t.header.frame_id, t.child_frame_id) for t in ros.transforms] == [("world", "body/wand")]
    assert ros.transforms[0].transform.translation.z == TURN.translation[2]


def cloud_table(ros) -> np.ndarray:
    """The points of a PointCloud2 read by its own field table (name, offset, datatype 7 = float32, 6 = uint32)."""
    formats = {7: "<f4", 6: "<u4"}
    layout = np.dtype({"names": [f.name for f in ros.fields], "formats": [formats[f.datatype] for f in ros.fields],
                       "offsets": [f.offset for f in ros.fields], "itemsize": ros.point_step})
    return np.frombuffer(bytes(ros.data), dtype=layout)


def test_triangulated_points_and_coloured_map_points_are_point_clouds():
    xyz = np.array([[0.5, -1.0, 2.0], [1.0, 2.0, 3.0], [-0.25, 0.0, 4.0]])
    points = Points3D(header=HEADER, points=xyz, residual_px=np.zeros(3, np.float32), views=np.full(3, 2, np.uint8),
                      covariances=np.zeros((3, 3, 3)), body=np.full(3, -1, np.int32))
    ros = round_trip(points_message(points), "sensor_msgs/msg/PointCloud2")
    table = cloud_table(ros)
    assert (ros.height, ros.width, len(table)) == (1, 3, 3)
    assert np.array_equal(np.stack([table["x"], table["y"], table["z"]], axis=1), xyz.astype(np.float32))
    colours = np.array([[255, 0, 0], [0, 128, 0], [1, 2, 3]], np.uint8)  # BGR
    cloud = PointCloud(header=HEADER, points=xyz.astype(np.float32), ids=np.arange(3), colors=colours)
    table = cloud_table(round_trip(map_message(cloud), "sensor_msgs/msg/PointCloud2"))
    assert table["rgb"].tolist() == [0x0000FF, 0x008000, 0x030201]


@pytest.mark.parametrize(("key", "topic"), [
    ("cam0/image", "/cam0/image_raw"), ("cam0/camera_info", "/cam0/camera_info"), ("cam0/overlay", "/cam0/overlay"),
    ("pose/cam0/marker/3", "/pose/cam0/marker_3"), ("pose/body/wand-2", "/pose/body/wand_2"),
    ("pose/slam/cam0", "/pose/slam/cam0"), ("points", "/points"), ("3d/map", "/n3d/map"),
])
def test_keys_become_topic_names_ros_accepts(key, topic):
    assert ros_topic(key) == topic


def bag_messages(folder):
    """``{topic: (type, [deserialized messages])}`` of a bag, by rosbags' reader."""
    found: dict[str, tuple[str, list]] = {}
    with Reader(folder) as reader:
        for connection, _, data in reader.messages():
            found.setdefault(connection.topic, (connection.msgtype, []))[1].append(
                TYPESTORE.deserialize_cdr(data, connection.msgtype))
    return found


def recorded(path, key):
    return [decode(m.message.data) for m in Scan(path).messages() if m.channel.topic == f"ar/rig0/{key}"]


def test_a_shipped_recording_reads_back_from_its_bag(tmp_path):
    done = export_rosbag(MARKERS, tmp_path / "bag")
    assert sorted(p.name for p in (tmp_path / "bag").iterdir()) == ["bag.mcap", "metadata.yaml"]
    bag = bag_messages(tmp_path / "bag")
    assert {topic: (msgtype, len(messages)) for topic, (msgtype, messages) in bag.items()} == {
        "/cam0/image_raw": ("sensor_msgs/msg/Image", 150), "/cam0/camera_info": ("sensor_msgs/msg/CameraInfo", 150),
        "/cam0/truth": ("tf2_msgs/msg/TFMessage", 150), "/tf_static": ("tf2_msgs/msg/TFMessage", 1)}
    placed = bag["/tf_static"][1][0].transforms
    assert [(e.header.frame_id, e.child_frame_id) for e in placed] == [("world", "rig"), ("rig", "cam0")]
    assert done.left_out == {"node/capture/stats": 5, "node/recorder/stats": 8} and done.damage is None
    with open(tmp_path / "bag" / "bag.mcap", "rb") as file:  # what a stock MCAP reader (Foxglove's) sees
        reader = make_reader(file)
        summary = reader.get_summary()
        assert reader.get_header().profile == "ros2" and summary is not None
        assert {(c.message_encoding, summary.schemas[c.schema_id].encoding) for c in summary.channels.values()} \
            == {("cdr", "ros2msg")}
    image, info, truth = (recorded(MARKERS, key)[-1] for key in ("cam0/image", "cam0/camera_info", "cam0/truth"))
    ros_image = bag["/cam0/image_raw"][1][-1]
    assert (ros_image.encoding, ros_image.width, ros_image.height) == ("mono8", 640, 480)
    assert bytes(ros_image.data) == image.data.tobytes()
    assert ros_image.header.stamp.sec * 10**9 + ros_image.header.stamp.nanosec == image.header.stamp_ns
    assert bag["/cam0/camera_info"][1][-1].k.tolist() == list(info.k)
    edges = bag["/cam0/truth"][1][-1].transforms
    assert [(e.header.frame_id, e.child_frame_id) for e in edges] == [(t.parent_frame, t.child_frame)
                                                                    for t in truth.transforms]
    first = edges[0].transform.translation
    assert (first.x, first.y, first.z) == truth.transforms[0].transform.translation


def test_estimated_poses_go_to_their_topic_and_to_tf(tmp_path):
    path = tmp_path / "poses.mcap"
    with open(path, "wb") as file:
        writer = Writer(file)
        writer.start()
        channel = writer.register_channel("pose/cam0/marker/3", "json", 0)
        for seq, state in enumerate((TrackingState.TRACKING, TrackingState.LOST, TrackingState.PREDICTED)):
            pose = Pose(header=HEADER.model_copy(update={"seq": seq}), child_frame_id="marker/3", transform=TURN,
                        state=state)
            writer.add_message(channel, log_time=seq, data=encode(pose), publish_time=seq)
        writer.finish()
    done = export_rosbag(path, tmp_path / "bag")
    assert done.topics == {"/pose/cam0/marker_3": 1, "/tf": 1}
    tf = bag_messages(tmp_path / "bag")["/tf"][1][0].transforms[0]
    assert (tf.header.frame_id, tf.child_frame_id) == ("cam0", "marker/3")


def test_a_slam_camera_keeps_one_parent_its_map_hanging_under_it(tmp_path):
    path = tmp_path / "slam.mcap"
    T_map_cam = Transform(translation=(0.3, 0.0, -0.1))
    with open(path, "wb") as file:
        writer = Writer(file)
        writer.start()
        infos, poses = (writer.register_channel(key, "json", 0) for key in ("cam0/camera_info", "pose/slam/cam0"))
        for seq in range(2):
            header = HEADER.model_copy(update={"seq": seq})
            info = CameraInfo(header=header, width=64, height=48, k=(50.0, 0, 32, 0, 50.0, 24, 0, 0, 1),
                              T_rig_camera=TURN)
            writer.add_message(infos, log_time=2 * seq, data=encode(info), publish_time=2 * seq)
            pose = Pose(header=header.model_copy(update={"frame_id": "map"}), child_frame_id="cam0",
                        transform=T_map_cam)
            writer.add_message(poses, log_time=2 * seq + 1, data=encode(pose), publish_time=2 * seq + 1)
        writer.finish()
    export_rosbag(path, tmp_path / "bag")
    bag = bag_messages(tmp_path / "bag")
    edges = [(t.header.frame_id, t.child_frame_id, t.transform) for topic in ("/tf_static", "/tf")
             for message in bag[topic][1] for t in message.transforms]
    assert sorted({(parent, child) for parent, child, _ in edges}) == [("cam0", "map"), ("rig", "cam0"),
                                                                       ("world", "rig")]
    turned = edges[-1][2].translation
    assert (turned.x, turned.y, turned.z) == pytest.approx((-0.3, 0.0, 0.1))
    assert bag["/pose/slam/cam0"][1][0].header.frame_id == "map"


def test_a_damaged_recording_gives_its_intact_part_and_exit_3(tmp_path):
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(MARKERS.read_bytes()[: MARKERS.stat().st_size // 2])
    assert main(["export", str(cut), "--format", "rosbag2", "-o", str(tmp_path / "bag")]) == EXIT_DAMAGED
    counts = {topic: len(messages) for topic, (_, messages) in bag_messages(tmp_path / "bag").items()}
    assert 0 < counts["/cam0/image_raw"] < 150


def test_an_existing_bag_is_kept_unless_forced_and_a_folder_of_something_else_always(tmp_path, capsys):
    out = tmp_path / "bag"
    argv = ["export", str(MARKERS), "--format", "rosbag2", "-o", str(out)]
    assert main(argv) == 0
    written = (out / "bag.mcap").stat().st_mtime_ns
    assert main(argv) == 2 and f"{out} exists: give --force to overwrite it" in capsys.readouterr().err
    assert (out / "bag.mcap").stat().st_mtime_ns == written
    assert main([*argv, "--force"]) == 0
    other = tmp_path / "notes"
    other.mkdir()
    (other / "keep.txt").write_text("mine")
    assert main([*argv[:-1], str(other), "--force"]) == 2
    assert (other / "keep.txt").read_text() == "mine"
    shutil.rmtree(out)
    assert main([*argv, "--key", "cam0/image"]) == 2 and not out.exists()
