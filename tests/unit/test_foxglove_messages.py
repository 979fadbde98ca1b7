"""artrack messages as Foxglove messages, each decoded through its schema's own protobuf descriptors and held
against the message it comes from."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from protocol import (
    Blobs,
    CameraInfo,
    ErrorReport,
    FrameTransform,
    GroundTruth,
    Header,
    Image,
    ImageTarget,
    ImageTargets,
    Keypoints,
    MarkerDetections,
    PointCloud,
    Points3D,
    Pose,
    RigidBodies,
    RigidBody,
    StaticTransforms,
    TrackingState,
    Trajectory,
    Transform,
)
from services.convert import matrix_from_transform
from services.viewer.foxglove_messages import DEFAULT_OPTIONS, FoxgloveConversion, FoxgloveOptions
from tests.foxglove_decoding import parsed

STAMP_NS = 1_700_000_012_345_678_901
HEADER = Header(stamp_ns=STAMP_NS, frame_id="cam0", seq=7)
PLACED = Transform(translation=(0.1, -0.2, 0.3), rotation=(0.0, 0.0, 0.6, 0.8))


def shown(message, options: FoxgloveOptions = DEFAULT_OPTIONS) -> dict[str, object]:
    """``{topic: decoded protobuf message}`` of what shows ``message``."""
    return {topic: parsed(fox) for topic, fox in FoxgloveConversion(options)(message)}


def stamp_ns(decoded) -> int:
    return decoded.timestamp.seconds * 1_000_000_000 + decoded.timestamp.nanos


@pytest.mark.parametrize(("encoding", "dtype", "shape", "pixel_bytes"), [
    ("mono8", np.uint8, (5, 7), 1), ("mono16", np.uint16, (5, 7), 2), ("bgr8", np.uint8, (5, 7, 3), 3),
    ("bgra8", np.uint8, (5, 7, 4), 4)])
def test_an_image_keeps_its_pixels_frame_and_stamp(encoding, dtype, shape, pixel_bytes):
    pixels = np.random.default_rng(1).integers(0, np.iinfo(dtype).max, shape, dtype=dtype)
    (topic, raw), = shown(Image(header=HEADER, encoding=encoding, data=pixels)).items()
    assert topic == "/cam0/image"
    assert (raw.encoding, raw.width, raw.height, raw.step, raw.frame_id) == (encoding, 7, 5, 7 * pixel_bytes, "cam0")
    assert stamp_ns(raw) == STAMP_NS
    np.testing.assert_array_equal(np.frombuffer(raw.data, np.dtype(dtype).newbyteorder("<")).reshape(shape), pixels)


def test_a_compressed_image_decodes_to_the_frame():
    pixels = np.zeros((48, 64, 3), np.uint8)
    pixels[10:30, 20:50] = (40, 200, 90)
    jpeg = shown(Image(header=HEADER, encoding="bgr8", data=pixels), FoxgloveOptions(compressed=True))["/cam0/image"]
    assert (jpeg.format, jpeg.frame_id, stamp_ns(jpeg)) == ("jpeg", "cam0", STAMP_NS)
    back = cv2.imdecode(np.frombuffer(jpeg.data, np.uint8), cv2.IMREAD_COLOR)
    assert np.abs(back.astype(int) - pixels).mean() < 3
    deep = np.arange(48 * 64, dtype=np.uint16).reshape(48, 64) * 13
    png = shown(Image(header=HEADER, encoding="mono16", data=deep), FoxgloveOptions(compressed=True))["/cam0/image"]
    assert png.format == "png"
    np.testing.assert_array_equal(cv2.imdecode(np.frombuffer(png.data, np.uint8), cv2.IMREAD_UNCHANGED), deep)


def test_a_calibration_keeps_k_d_r_p_in_the_images_frame_and_places_the_camera_in_its_rig():
    k = (600.0, 0.0, 320.5, 0.0, 610.0, 240.25, 0.0, 0.0, 1.0)
    info = CameraInfo(header=HEADER, width=640, height=480, k=k, d=(0.1, -0.05, 0.001, 0.002, 0.01),
                      T_rig_camera=PLACED)
    found = shown(info)
    calibration = found["/cam0/camera_info"]
    assert (calibration.frame_id, calibration.width, calibration.height) == ("cam0", 640, 480)
    assert calibration.distortion_model == "plumb_bob" and stamp_ns(calibration) == STAMP_NS
    np.testing.assert_array_equal(calibration.K, k)
    np.testing.assert_array_equal(calibration.D, info.d)
    np.testing.assert_array_equal(calibration.R, info.r)
    np.testing.assert_array_equal(np.reshape(calibration.P, (3, 4)), np.c_[np.reshape(k, (3, 3)), np.zeros(3)])
    world, edge = found["/tf"].transforms
    assert (world.parent_frame_id, world.child_frame_id, world.rotation.w) == ("world", "rig", 1.0)
    assert (edge.parent_frame_id, edge.child_frame_id) == ("rig", "cam0")
    assert [edge.translation.x, edge.translation.y, edge.translation.z] == pytest.approx(PLACED.translation)
    fisheye = CameraInfo(header=HEADER, width=64, height=48, k=k, distortion_model="equidistant", d=(0.1, 0, 0, 0))
    assert shown(fisheye)["/cam0/camera_info"].distortion_model == "kannala_brandt"


def test_a_pose_is_a_pose_in_its_frame_and_a_transform():
    pose = Pose(header=HEADER, child_frame_id="marker/3", transform=PLACED)
    found = shown(pose)
    posed = found["/pose/cam0/marker/3"]
    assert posed.frame_id == "cam0" and stamp_ns(posed) == STAMP_NS
    p, q = posed.pose.position, posed.pose.orientation
    assert [p.x, p.y, p.z] == pytest.approx(PLACED.translation)
    assert [q.x, q.y, q.z, q.w] == pytest.approx(PLACED.rotation)
    (edge,) = found["/tf"].transforms
    assert (edge.parent_frame_id, edge.child_frame_id) == ("cam0", "marker/3")
    assert [edge.rotation.x, edge.rotation.y, edge.rotation.z, edge.rotation.w] == pytest.approx(PLACED.rotation)
    assert shown(Pose(header=HEADER, child_frame_id="marker/3", state=TrackingState.LOST)) == {}


def test_bodies_truth_and_static_transforms_become_frame_transforms():
    world = Header(stamp_ns=STAMP_NS, frame_id="world")
    bodies = RigidBodies(header=world, bodies=(RigidBody(name="wand", transform=PLACED),
                                               RigidBody(name="hidden", state=TrackingState.LOST)))
    (edge,) = shown(bodies)["/tf"].transforms
    assert (edge.parent_frame_id, edge.child_frame_id, edge.translation.z) == ("world", "body/wand", 0.3)
    truth = GroundTruth(header=HEADER, transforms=(FrameTransform(parent_frame="cam0", child_frame="marker/3",
                                                                  transform=PLACED),))
    (fact,) = shown(truth)["/cam0/truth"].transforms
    assert (fact.parent_frame_id, fact.child_frame_id, fact.translation.y) == ("cam0", "truth/marker/3", -0.2)
    static = StaticTransforms(header=Header(stamp_ns=STAMP_NS, frame_id="rig"), transforms=(
        FrameTransform(parent_frame="rig", child_frame="cam0", transform=Transform()),
        FrameTransform(parent_frame="rig", child_frame="cam1", transform=PLACED)))
    edges = shown(static)["/tf_static"].transforms
    assert [(e.parent_frame_id, e.child_frame_id) for e in edges] == [("rig", "cam0"), ("rig", "cam1")]
    assert edges[1].rotation.w == pytest.approx(0.8) and stamp_ns(edges[1]) == STAMP_NS


def tf_edges(convert: FoxgloveConversion, messages) -> dict[str, tuple[str, np.ndarray]]:
    """Every ``/tf`` and ``/tf_static`` edge ``messages`` give in turn: child -> (parent, (4, 4) T_parent_child),
    checking that no child ever gets a second parent."""
    edges: dict[str, tuple[str, np.ndarray]] = {}
    for message in messages:
        for topic, fox in convert(message):
            if topic not in ("/tf", "/tf_static"):
                continue
            for e in parsed(fox).transforms:
                assert edges.get(e.child_frame_id, (e.parent_frame_id,))[0] == e.parent_frame_id, e
                rotation = (e.rotation.x, e.rotation.y, e.rotation.z, e.rotation.w)
                edges[e.child_frame_id] = (e.parent_frame_id, matrix_from_transform(Transform(
                    translation=(e.translation.x, e.translation.y, e.translation.z), rotation=rotation)))
    return edges


def placed_in(edges: dict[str, tuple[str, np.ndarray]], frame: str, ancestor: str) -> np.ndarray:
    """``T_ancestor_frame`` composed along the tree's edges (KeyError when ``ancestor`` is not above ``frame``)."""
    T = np.eye(4)
    while frame != ancestor:
        frame, up = edges[frame]
        T = up @ T
    return T


def test_a_slam_camera_placed_on_its_rig_hangs_its_map_under_it_in_one_tree():
    info = CameraInfo(header=HEADER, width=64, height=48, k=(50.0, 0, 32, 0, 50.0, 24, 0, 0, 1), T_rig_camera=PLACED)
    map_header = HEADER.model_copy(update={"frame_id": "map"})
    T_map_cam = Transform(translation=(0.4, 0.1, -0.3), rotation=(0.0, 0.28, 0.0, 0.96))
    slam = Pose(header=map_header, child_frame_id="cam0", transform=T_map_cam)
    edges = tf_edges(FoxgloveConversion(), [info, slam, info, slam])
    assert {child: parent for child, (parent, _) in edges.items()} == {"rig": "world", "cam0": "rig", "map": "cam0"}
    np.testing.assert_allclose(np.linalg.inv(placed_in(edges, "map", "cam0")), matrix_from_transform(T_map_cam),
                               atol=1e-12)
    np.testing.assert_allclose(placed_in(edges, "cam0", "world"), matrix_from_transform(PLACED), atol=1e-12)


def test_bodies_and_cameras_of_a_fixed_rig_share_the_world_and_a_marker_seen_twice_stands_beside_itself():
    world = Header(stamp_ns=STAMP_NS, frame_id="world")
    infos = [CameraInfo(header=HEADER.model_copy(update={"frame_id": cam}), width=64, height=48,
                        k=(50.0, 0, 32, 0, 50.0, 24, 0, 0, 1), T_rig_camera=placed)
             for cam, placed in (("cam0", Transform()), ("cam1", PLACED))]
    bodies = RigidBodies(header=world, bodies=(RigidBody(name="wand", transform=PLACED),))
    seen = [Pose(header=HEADER.model_copy(update={"frame_id": cam}), child_frame_id="marker/3", transform=PLACED)
            for cam in ("cam0", "cam1")]
    edges = tf_edges(FoxgloveConversion(), [*infos, bodies, *seen])
    assert {child: parent for child, (parent, _) in edges.items()} == {
        "rig": "world", "cam0": "rig", "cam1": "rig", "body/wand": "world", "marker/3": "cam0",
        "cam1/marker/3": "cam1"}
    np.testing.assert_allclose(placed_in(edges, "cam1/marker/3", "cam1"), matrix_from_transform(PLACED))


def points3d() -> Points3D:
    n = 5
    return Points3D(header=Header(stamp_ns=STAMP_NS, frame_id="world"), bodies=("wand", "head"),
                    points=np.arange(3 * n, dtype=np.float64).reshape(n, 3) / 10, residual_px=np.zeros(n, np.float32),
                    views=np.full(n, 2, np.uint8), covariances=np.zeros((n, 3, 3)),
                    body=np.array([0, 0, -1, 1, 0], np.int32))


def test_triangulated_points_are_a_cloud_and_spheres_by_body():
    points = points3d()
    found = shown(points)
    cloud = found["/world/points"]
    assert (cloud.frame_id, cloud.point_stride, [f.name for f in cloud.fields]) == ("world", 12, ["x", "y", "z"])
    xyz = np.frombuffer(cloud.data, "<f4").reshape(-1, 3)
    assert len(xyz) == 5
    np.testing.assert_allclose(xyz, points.points, rtol=1e-6)
    entities = {e.id: e for e in found["/world/spheres"].entities}
    assert {name: len(e.spheres) for name, e in entities.items()} == {"body/wand": 3, "body/head": 1, "unlabelled": 1}
    head = entities["body/head"].spheres[0]
    assert [head.pose.position.x, head.pose.position.y, head.pose.position.z] == pytest.approx(points.points[3])


def test_map_points_keep_their_colours_as_rgb():
    bgr = np.array([[255, 0, 0], [0, 0, 255]], np.uint8)
    cloud = PointCloud(header=Header(stamp_ns=STAMP_NS, frame_id="map"), points=np.eye(2, 3, dtype=np.float32),
                       ids=np.arange(2), colors=bgr)
    packed = shown(cloud)["/map/map"]
    assert packed.point_stride == 16 and [f.name for f in packed.fields][3:] == ["red", "green", "blue", "alpha"]
    rows = np.frombuffer(packed.data, np.dtype([("xyz", "<f4", 3), ("rgba", "u1", 4)]))
    np.testing.assert_array_equal(rows["xyz"], cloud.points)
    np.testing.assert_array_equal(rows["rgba"], [[0, 0, 255, 255], [255, 0, 0, 255]])


def test_a_slam_trajectory_is_its_poses_in_the_map_frame():
    poses = np.stack([matrix_from_transform(Transform(translation=(0.5 * i, 0.0, 1.0),
                                                      rotation=(0.0, np.sin(0.1 * i), 0.0, np.cos(0.1 * i))))
                      for i in range(3)])
    trajectory = Trajectory(header=Header(stamp_ns=STAMP_NS, frame_id="map"), child_frame_id="cam0",
                            stamps_ns=np.arange(3), seqs=np.arange(3), poses=poses)
    shown_poses = shown(trajectory)["/map/trajectory/cam0"]
    assert shown_poses.frame_id == "map" and len(shown_poses.poses) == 3
    for pose, T in zip(shown_poses.poses, poses, strict=True):
        q, t = pose.orientation, pose.position
        back = matrix_from_transform(Transform(translation=(t.x, t.y, t.z), rotation=(q.x, q.y, q.z, q.w)))
        assert back == pytest.approx(T, abs=1e-12)


def test_markers_are_outlines_in_the_image_and_squares_in_their_frames():
    corners = np.array([[[10, 20], [30, 20], [30, 40], [10, 40]], [[50, 5], [60, 5], [60, 15], [50, 15]]], np.float32)
    found = shown(MarkerDetections(header=HEADER, dictionary="DICT_4X4_50", ids=np.array([3, 9], np.int32),
                                   corners=corners, quality=np.ones(2, np.float32),
                                   side_m=np.array([0.05, 0.0], np.float32)))
    drawn = found["/cam0/markers"]
    assert stamp_ns(drawn) == STAMP_NS
    np.testing.assert_array_equal([[(p.x, p.y) for p in outline.points] for outline in drawn.points], corners)
    assert [t.text for t in drawn.texts] == ["3", "9"]
    (square,) = found["/cam0/marker_outlines"].entities  # marker 9's side is unknown: no square
    assert (square.id, square.frame_id, square.frame_locked) == ("marker/3", "marker/3", True)
    xs = [p.x for p in square.lines[0].points]
    assert max(xs) - min(xs) == pytest.approx(0.05)


def test_image_targets_are_outlines_and_planes_locked_to_their_frames():
    w, h = 0.297, 0.21  # A4 landscape, origin at the centre, y up
    centred = ((-w / 2, h / 2, 0.0), (w / 2, h / 2, 0.0), (w / 2, -h / 2, 0.0), (-w / 2, -h / 2, 0.0))
    cornered = ((0.0, 0.0, 0.0), (0.1, 0.0, 0.0), (0.1, 0.05, 0.0), (0.0, 0.05, 0.0))  # origin top-left, y down
    described = ImageTargets(header=HEADER, targets=(
        ImageTarget(name="poster", frame_id="target/poster", width_m=w, height_m=h, corners=centred),
        ImageTarget(name="card", frame_id="target/card", width_m=0.1, height_m=0.05, corners=cornered)))
    (topic, update), = shown(described).items()
    assert topic == "/cam0/target_outlines"
    poster, card = update.entities
    assert (poster.id, poster.frame_id, poster.frame_locked) == ("target/poster", "target/poster", True)
    assert stamp_ns(poster) == STAMP_NS and poster.lifetime.ToNanoseconds() == 0
    (outline,) = poster.lines
    line_types = outline.DESCRIPTOR.fields_by_name["type"].enum_type.values_by_number
    assert line_types[outline.type].name == "LINE_LOOP"  # the last corner joins the first
    xyz = np.array([[p.x, p.y, p.z] for p in outline.points])
    np.testing.assert_allclose(xyz, [[-w / 2, h / 2, 0], [w / 2, h / 2, 0], [w / 2, -h / 2, 0], [-w / 2, -h / 2, 0]])
    (plane,) = poster.triangles
    assert plane.color.a < 1.0
    triangles = np.array([[p.x, p.y, p.z] for p in plane.points])[list(plane.indices)].reshape(2, 3, 3)
    area = sum(0.5 * np.linalg.norm(np.cross(t[1] - t[0], t[2] - t[0])) for t in triangles)
    assert area == pytest.approx(w * h)
    assert card.frame_id == "target/card"
    np.testing.assert_allclose([[p.x, p.y, p.z] for p in card.lines[0].points], cornered)


def test_blobs_and_keypoints_are_image_annotations():
    blobs = Blobs(header=HEADER, centroids=np.array([[10.5, 20.25], [3.0, 4.0]]), areas=np.ones(2, np.float32),
                  radii=np.array([2.0, 3.5], np.float32), quality=np.ones(2, np.float32),
                  flags=np.array([0, 1], np.uint8))
    circles = shown(blobs)["/cam0/blobs"].circles
    assert [(c.position.x, c.position.y, c.diameter) for c in circles] == [(10.5, 20.25, 4.0), (3.0, 4.0, 7.0)]
    assert circles[0].outline_color != circles[1].outline_color
    keypoints = Keypoints(header=HEADER, points=np.array([[1, 2], [3, 4], [5, 6]], np.float32),
                          sizes=np.ones(3, np.float32), angles=np.zeros(3, np.float32),
                          responses=np.ones(3, np.float32), descriptors=np.zeros((3, 0), np.uint8))
    (points,) = shown(keypoints)["/cam0/keypoints"].points
    assert [(p.x, p.y) for p in points.points] == [(1, 2), (3, 4), (5, 6)]
    assert stamp_ns(points) == STAMP_NS


def test_an_error_report_is_a_warning_log_named_after_its_node():
    report = ErrorReport(header=HEADER, node="marker-cam0", kind="decode", detail="bad payload", key="ar/x", count=2)
    entry = shown(report)["/log"]
    assert (entry.name, entry.level, stamp_ns(entry)) == ("marker-cam0", 3, STAMP_NS)  # 3: WARNING
    assert entry.message == "decode on ar/x: bad payload (2 so far)"
