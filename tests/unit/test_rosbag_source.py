"""``rosbag2:DIR`` sources: ROS 2 images and camera infos as arrays and camera models, and bags exported from
the shipped recordings read back frame by frame."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from rosbags.rosbag2 import StoragePlugin, Writer

from protocol.codec import decode
from services.capture.rosbag import camera_from_info, camera_name, image_array
from services.capture.sources import SourceError, camera_names, check_source, frame_count, frame_sizes, open_source
from services.geometry.se3 import from_quaternion_translation
from services.recorder.reading import Scan
from services.recorder.rosbag import TYPESTORE, export_rosbag, ros_time
from tests.integration.support import ROOT

T = TYPESTORE.types
RECORDINGS = ROOT / "recordings"


def ros_image(encoding: str, pixels: np.ndarray, *, step: int | None = None, big: bool = False):
    """A ``sensor_msgs/msg/Image`` of ``pixels`` (rows padded to ``step`` bytes), written by hand."""
    data = pixels.astype(pixels.dtype.newbyteorder(">" if big else "<"))
    rows = data.reshape(pixels.shape[0], -1).view(np.uint8)
    step = step or rows.shape[1]
    padded = np.zeros((pixels.shape[0], step), np.uint8)
    padded[:, : rows.shape[1]] = rows
    header = T["std_msgs/msg/Header"](stamp=ros_time(5), frame_id="cam")
    return T["sensor_msgs/msg/Image"](header=header, height=pixels.shape[0], width=pixels.shape[1],
                                      encoding=encoding, is_bigendian=int(big), step=step, data=padded.reshape(-1))


PIXELS = np.arange(2 * 3 * 3, dtype=np.uint8).reshape(2, 3, 3)


@pytest.mark.parametrize(("message", "expected"), [
    (ros_image("mono8", PIXELS[..., 0], step=8), PIXELS[..., 0]),
    (ros_image("bgr8", PIXELS), PIXELS),
    (ros_image("rgb8", PIXELS, step=12), PIXELS[..., ::-1]),
    (ros_image("mono16", PIXELS[..., 0].astype(np.uint16) * 1000, big=True), PIXELS[..., 0].astype(np.uint16) * 1000),
    (ros_image("mono16", PIXELS[..., 0].astype(np.uint16) * 1000), PIXELS[..., 0].astype(np.uint16) * 1000),
], ids=["mono8-padded", "bgr8", "rgb8-padded", "mono16-big-endian", "mono16"])
def test_ros_images_become_the_arrays_opencv_holds(message, expected):
    image = image_array(message)
    assert image.dtype == expected.dtype and np.array_equal(image, expected)


def test_compressed_images_decode_and_unknown_encodings_are_named():
    png = cv2.imencode(".png", PIXELS)[1]
    header = T["std_msgs/msg/Header"](stamp=ros_time(0), frame_id="cam")
    assert np.array_equal(image_array(T["sensor_msgs/msg/CompressedImage"](header=header, format="png", data=png)),
                          PIXELS)
    with pytest.raises(ValueError, match="image encoding 'bayer_rggb8' is not one artrack reads"):
        image_array(ros_image("bayer_rggb8", PIXELS[..., 0]))


def camera_info(k, d=(0.1, -0.2, 0.0, 0.0), model="plumb_bob"):
    header = T["std_msgs/msg/Header"](stamp=ros_time(0), frame_id="cam")
    roi = T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    return T["sensor_msgs/msg/CameraInfo"](header=header, height=480, width=640, distortion_model=model,
                                           d=np.array(d, float), k=np.array(k, float), r=np.eye(3).ravel(),
                                           p=np.zeros(12), binning_x=0, binning_y=0, roi=roi)


def test_camera_infos_become_camera_models():
    k = (500.0, 0.0, 320.0, 0.0, 505.0, 240.0, 0.0, 0.0, 1.0)
    camera = camera_from_info(camera_info(k), "cam0")
    assert camera is not None
    assert (camera.name, camera.width, camera.height) == ("cam0", 640, 480)
    assert camera.K.ravel().tolist() == list(k) and camera.dist.tolist() == [0.1, -0.2, 0.0, 0.0, 0.0]
    assert camera_from_info(camera_info(np.zeros(9)), "cam0") is None  # an uncalibrated driver's
    with pytest.raises(ValueError, match="distortion model 'equidistant'"):
        camera_from_info(camera_info(k, model="equidistant"), "cam0")


@pytest.mark.parametrize(("topic", "name"), [("/cam0/image_raw", "cam0"), ("/stereo/left/image_raw", "stereo_left"),
                                             ("/image_raw", "cam0")])
def test_cameras_are_named_after_their_topic_namespace(topic, name):
    assert camera_name(topic) == name


@pytest.fixture(scope="module")
def bags(tmp_path_factory):
    folder = tmp_path_factory.mktemp("bags")
    for name in ("markers", "ir_rig"):
        export_rosbag(RECORDINGS / f"{name}.mcap", folder / name)
    return folder


def recorded(path, key):
    return [decode(m.message.data) for m in Scan(path).messages() if m.channel.topic == f"ar/rig0/{key}"]


def test_a_bag_plays_the_recording_it_was_exported_from(bags):
    uri = f"rosbag2:{bags / 'markers'}"
    assert check_source(uri) == ("rosbag2", str(bags / "markers"))
    assert camera_names((uri,), {}) == ["cam0"] and frame_sizes((uri,), {}) == [(640, 480)]
    assert frame_count(uri) == 150
    source = open_source(uri)
    images, info = recorded(RECORDINGS / "markers.mcap", "cam0/image"), recorded(RECORDINGS / "markers.mcap",
                                                                                   "cam0/camera_info")[0]
    assert source.calibration["cam0"].K.ravel().tolist() == list(info.k)
    frames = list(source.frames())
    assert len(frames) == 150
    assert [f.time_ns for f in frames] == [m.header.stamp_ns for m in images]
    assert all(np.array_equal(f.images["cam0"], m.data) for f, m in zip(frames[::30], images[::30], strict=True))


def test_the_cameras_of_a_rig_bag_go_in_step_or_one_is_chosen(bags):
    uri = f"rosbag2:{bags / 'ir_rig'}"
    source = open_source(uri)
    assert source.camera_names == ("cam0", "cam1") and set(source.calibration) == {"cam0", "cam1"}
    frames = list(source.frames())
    assert len(frames) == 60 and all(set(f.images) == {"cam0", "cam1"} for f in frames)
    cam1 = recorded(RECORDINGS / "ir_rig.mcap", "cam1/image")
    assert np.array_equal(frames[7].images["cam1"], cam1[7].data)
    one = open_source(f"{uri}?topic=/cam1/image_raw")
    assert one.camera_names == ("cam1",) and len(list(one.frames())) == 60


def test_a_missing_folder_a_folder_that_is_no_bag_and_a_bag_without_images_are_refused_in_one_line(tmp_path, bags):
    with pytest.raises(SourceError, match=f"^rosbag2:{tmp_path}/none: no such folder$"):
        check_source(f"rosbag2:{tmp_path}/none")
    with pytest.raises(SourceError, match=r"not a ROS 2 bag \(no metadata.yaml\)$"):
        check_source(f"rosbag2:{tmp_path}")
    with pytest.raises(SourceError, match="/cam9/image_raw is not an image topic of the bag"):
        check_source(f"rosbag2:{bags / 'markers'}?topic=/cam9/image_raw")
    with Writer(tmp_path / "tf_only", version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        connection = writer.add_connection("/tf", "tf2_msgs/msg/TFMessage", typestore=TYPESTORE)
        writer.write(connection, 1, TYPESTORE.serialize_cdr(T["tf2_msgs/msg/TFMessage"](transforms=[]),
                                                            "tf2_msgs/msg/TFMessage"))
    with pytest.raises(SourceError, match=r"no image topic .* \(topics: /tf \(tf2_msgs/msg/TFMessage\)\)$") as raised:
        check_source(f"rosbag2:{tmp_path / 'tf_only'}")
    assert "\n" not in str(raised.value)


def test_a_rig_bag_places_its_cameras_as_the_recording_did(bags):
    calibration = open_source(f"rosbag2:{bags / 'ir_rig'}").calibration
    for camera in ("cam0", "cam1"):
        info = recorded(RECORDINGS / "ir_rig.mcap", f"{camera}/camera_info")[0]
        expected = from_quaternion_translation(np.array(info.T_rig_camera.rotation),
                                               np.array(info.T_rig_camera.translation))
        assert np.allclose(calibration[camera].T_rig_camera, expected, atol=1e-12), camera
    assert not np.allclose(calibration["cam1"].T_rig_camera, np.eye(4))  # a rig: the second camera is elsewhere


def test_a_truncated_bag_is_refused_in_one_line(tmp_path, bags):
    cut = tmp_path / "cut"
    cut.mkdir()
    (cut / "metadata.yaml").write_text((bags / "markers" / "metadata.yaml").read_text().replace("markers.mcap",
                                                                                                 "cut.mcap"))
    whole = (bags / "markers" / "markers.mcap").read_bytes()
    (cut / "cut.mcap").write_bytes(whole[: len(whole) // 2])
    with pytest.raises(SourceError, match=f"^rosbag2:{cut}: cannot read the bag ") as raised:
        check_source(f"rosbag2:{cut}")
    assert "\n" not in str(raised.value)
