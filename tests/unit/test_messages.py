"""Message validation: what each message type accepts and refuses, registry, JSON views."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from hypothesis import given, settings
from pydantic import ValidationError
from strategies import quaternions

from protocol import (
    Blobs,
    CameraInfo,
    DecodeError,
    Header,
    Image,
    ImageTarget,
    ImageTargets,
    Keyframes,
    Keypoints,
    MarkerDetections,
    Message,
    NodeStats,
    PointCloud,
    Pose,
    PoseQuality,
    RigidBodies,
    RigidBody,
    StageTimings,
    TrackingState,
    Transform,
    decode,
    encode,
    message_type,
    to_json,
)

HEADER = Header(stamp_ns=1_700_000_000_000_000_000, frame_id="cam0", seq=3)
K = (500.0, 0.0, 320.0, 0.0, 500.0, 240.0, 0.0, 0.0, 1.0)


def f32(*shape: int) -> np.ndarray:
    return np.zeros(shape, np.float32)


# --- header, immutability, registry ---


def test_header_refuses_negative_stamp_and_seq():
    with pytest.raises(ValidationError, match="stamp_ns"):
        Header(stamp_ns=-1)
    with pytest.raises(ValidationError, match="seq"):
        Header(stamp_ns=0, seq=-1)


def test_messages_are_frozen_and_refuse_unknown_fields():
    pose = Pose(header=HEADER, child_frame_id="marker/7")
    with pytest.raises(ValidationError, match="frozen"):
        pose.child_frame_id = "marker/8"
    with pytest.raises(ValidationError, match="Extra inputs are not permitted"):
        Pose(header=HEADER, child_frame_id="marker/7", colour="red")


@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf])
def test_float_fields_refuse_values_json_cannot_carry(value: float):
    with pytest.raises(ValidationError, match="processing_ms_p50"):
        NodeStats(header=HEADER, node="n", kind="k", host="h", pid=1, uptime_s=1.0, processing_ms_p50=value)
    with pytest.raises(ValidationError, match="reprojection_rms_px"):
        PoseQuality(reprojection_rms_px=value)
    with pytest.raises(ValidationError, match="d.0"):
        CameraInfo(header=HEADER, width=640, height=480, k=K, d=(value, 0.0, 0.0, 0.0))


def test_registry_finds_classes_by_schema_name():
    assert message_type("artrack.Pose") is Pose
    assert message_type("artrack.Nope") is None


def test_a_second_class_with_a_taken_schema_name_is_refused():
    with pytest.raises(TypeError, match="'artrack.Pose' already registered"):

        class Impostor(Message):
            SCHEMA = "artrack.Pose"
            VERSION = 1

    assert message_type("artrack.Pose") is Pose


def test_a_schema_without_a_version_is_refused():
    with pytest.raises(TypeError, match="must set VERSION"):

        class Unversioned(Message):
            SCHEMA = "test.Unversioned"

    assert message_type("test.Unversioned") is None


# --- Image ---


@pytest.mark.parametrize(
    ("encoding", "data"),
    [
        ("mono8", np.zeros((2, 3), np.uint8)),
        ("mono16", np.zeros((2, 3), np.uint16)),
        ("bgr8", np.zeros((2, 3, 3), np.uint8)),
        ("bgra8", np.zeros((2, 3, 4), np.uint8)),
    ],
)
def test_image_accepts_matching_encoding(encoding: str, data: np.ndarray):
    image = Image(header=HEADER, encoding=encoding, data=data)
    assert (image.height, image.width) == (2, 3)


@pytest.mark.parametrize(
    ("encoding", "data", "expected"),
    [
        ("mono8", np.zeros((2, 3), np.uint16), "mono8 needs uint8 with 1 channel(s), got uint16 with 1"),
        ("mono16", np.zeros((2, 3), np.uint8), "encoding mono16 needs uint16"),
        ("bgr8", np.zeros((2, 3), np.uint8), "encoding bgr8 needs uint8 with 3 channel(s), got uint8 with 1"),
        ("bgr8", np.zeros((2, 3, 4), np.uint8), "got uint8 with 4"),
        ("bgra8", np.zeros((2, 3, 3), np.uint8), "got uint8 with 3"),
        ("mono8", np.zeros((2, 3, 2), np.uint8), "does not fit (N, N) or (N, N, 3) or (N, N, 4)"),
        ("mono8", np.zeros(6, np.uint8), "does not fit"),
        ("mono8", np.zeros((2, 3), np.int32), "dtype int32 not in ['uint8', 'uint16']"),
        ("mono8", [[0, 1], [2, 3]], "dtype int64 not in"),  # a list is not guessed into one of two dtypes
        ("rgb8", np.zeros((2, 3, 3), np.uint8), "encoding"),
    ],
)
def test_image_refuses_mismatched_layout(encoding: str, data: object, expected: str):
    with pytest.raises(ValidationError) as caught:
        Image(header=HEADER, encoding=encoding, data=data)
    assert expected in str(caught.value)


def test_arrays_are_held_in_native_byte_order():
    big_endian = np.arange(6, dtype=">u2").reshape(2, 3)
    image = Image(header=HEADER, encoding="mono16", data=big_endian)
    assert image.data.dtype == np.dtype(np.uint16)
    assert image.data.tolist() == big_endian.tolist()


# --- CameraInfo ---

DISTORTION = [
    ("plumb_bob", 0, True),
    ("plumb_bob", 4, True),
    ("plumb_bob", 5, True),
    ("plumb_bob", 8, False),
    ("plumb_bob", 3, False),
    ("rational_polynomial", 8, True),
    ("rational_polynomial", 5, False),
    ("equidistant", 4, True),
    ("equidistant", 5, False),
    ("equidistant", 0, False),
]


@pytest.mark.parametrize(("model", "count", "valid"), DISTORTION)
def test_camera_info_distortion_count_follows_model(model: str, count: int, valid: bool):
    def build() -> CameraInfo:
        return CameraInfo(header=HEADER, width=640, height=480, k=K, distortion_model=model,
                          d=(0.01,) * count)

    if valid:
        assert len(build().d) == count
    else:
        with pytest.raises(ValidationError, match=f"{model} takes .* distortion coefficients, got {count}"):
            build()


@pytest.mark.parametrize(
    "k",
    [
        (0.0, 0.0, 320.0, 0.0, 500.0, 240.0, 0.0, 0.0, 1.0),
        (500.0, 0.0, 320.0, 0.0, -500.0, 240.0, 0.0, 0.0, 1.0),
        (500.0, 0.0, 320.0, 0.0, 500.0, 240.0, 0.0, 0.0, 2.0),
    ],
)
def test_camera_info_refuses_a_bad_camera_matrix(k: tuple[float, ...]):
    with pytest.raises(ValidationError, match="fx, fy > 0 and k\\[8\\] = 1"):
        CameraInfo(header=HEADER, width=640, height=480, k=k)


@pytest.mark.parametrize(("width", "height"), [(0, 480), (640, 0), (-1, 480)])
def test_camera_info_refuses_empty_images(width: int, height: int):
    with pytest.raises(ValidationError):
        CameraInfo(header=HEADER, width=width, height=height, k=K)


# --- Transform and Pose ---


def test_transform_normalises_a_nearly_unit_quaternion():
    transform = Transform(rotation=(0.0, 0.0, 0.6 * 1.0005, 0.8 * 1.0005))
    assert transform.rotation == pytest.approx((0.0, 0.0, 0.6, 0.8), abs=1e-15)
    assert math.hypot(*transform.rotation) == pytest.approx(1.0, abs=1e-15)


@settings(max_examples=200, deadline=None)
@given(quaternions())
def test_transform_normalisation_is_idempotent(rotation: tuple[float, float, float, float]):
    once = Transform(rotation=rotation).rotation
    assert Transform(rotation=once).rotation == once


@pytest.mark.parametrize(
    "rotation", [(0.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.01), (1.0, 1.0, 0.0, 0.0), (0.0, 0.0, 0.0, 0.99)]
)
def test_transform_refuses_a_non_unit_quaternion(rotation: tuple[float, ...]):
    with pytest.raises(ValidationError, match="rotation quaternion \\(x, y, z, w\\) must have unit norm"):
        Transform(rotation=rotation)


def test_transform_refuses_non_finite_numbers():
    with pytest.raises(ValidationError, match="translation"):
        Transform(translation=(0.0, math.inf, 0.0))
    with pytest.raises(ValidationError, match="rotation"):
        Transform(rotation=(math.nan, 0.0, 0.0, 1.0))


def test_transform_defaults_to_identity():
    assert Transform() == Transform(translation=(0, 0, 0), rotation=(0, 0, 0, 1))


@pytest.mark.parametrize("covariance", [None, tuple(float(i) for i in range(36))])
def test_pose_accepts_no_covariance_or_a_6x6_one(covariance: tuple[float, ...] | None):
    assert Pose(header=HEADER, child_frame_id="body/wand", covariance=covariance).covariance == covariance


@pytest.mark.parametrize("covariance", [(), (0.0,) * 6, (0.0,) * 35, (0.0,) * 37])
def test_pose_refuses_a_covariance_that_is_not_6x6(covariance: tuple[float, ...]):
    with pytest.raises(ValidationError, match="covariance must hold 36 finite numbers"):
        Pose(header=HEADER, child_frame_id="body/wand", covariance=covariance)


def test_a_lost_pose_says_why_and_a_recognised_one_travels_at_version_4():
    lost = Pose(header=HEADER, child_frame_id="target/poster", state="lost", reason="too_few_matches")
    recognised = Pose(header=HEADER, child_frame_id="target/poster", state="recognised")
    assert decode(encode(lost)) == lost and decode(encode(recognised)).state == "recognised"
    assert b'"version":4' in encode(lost)


def test_a_pose_of_version_2_still_decodes_with_no_reason():
    old = encode(Pose(header=HEADER, child_frame_id="marker/7")).replace(b'"version":4', b'"version":2')
    assert decode(old).reason == "" and decode(old).state == "tracking"


def test_a_state_spelled_initializing_by_older_versions_decodes_as_initialising():
    """Pose versions 1 to 3 and RigidBodies versions 1 and 2 (older recordings) wrote ``initializing``."""
    pose = Pose(header=HEADER, child_frame_id="cam0", state=TrackingState.INITIALISING, reason="low_parallax")
    assert b'"state":"initialising"' in encode(pose)
    for version in (1, 2, 3):
        document = {**json.loads(encode(pose)), "version": version, "state": "initializing"}
        if version < 3:  # no reason before version 3
            del document["reason"]
        assert decode(json.dumps(document).encode()) == pose.model_copy(update={"reason": document.get("reason", "")})
    bodies = RigidBodies(header=HEADER, bodies=(RigidBody(name="wand", state=TrackingState.INITIALISING),))
    for version in (1, 2):
        document = json.loads(encode(bodies))
        document["version"], document["bodies"][0]["state"] = version, "initializing"
        assert decode(json.dumps(document).encode()) == bodies


# --- detections ---


def markers(n_ids: int = 2, n_corners: int = 2, n_quality: int = 2, n_sides: int = 2) -> MarkerDetections:
    return MarkerDetections(header=HEADER, dictionary="DICT_4X4_50", ids=np.arange(n_ids, dtype=np.int32),
                            corners=f32(n_corners, 4, 2), quality=f32(n_quality), side_m=f32(n_sides))


def blobs(n_centroids: int, n_others: int) -> Blobs:
    return Blobs(header=HEADER, centroids=np.zeros((n_centroids, 2)), areas=f32(n_others), radii=f32(n_others),
                 quality=f32(n_others), flags=np.zeros(n_others, np.uint8))


def test_detections_with_zero_rows_are_valid():
    assert len(markers(0, 0, 0, 0).ids) == 0
    assert len(blobs(0, 0).radii) == 0


@pytest.mark.parametrize("counts", [(3, 2, 2, 2), (2, 3, 2, 2), (2, 2, 1, 2), (2, 2, 2, 0)])
def test_marker_detections_refuse_mismatched_rows(counts: tuple[int, int, int, int]):
    with pytest.raises(ValidationError, match="arrays must have the same number of rows"):
        markers(*counts)


def test_marker_ids_given_as_a_list_become_int32():
    detections = MarkerDetections(header=HEADER, dictionary="", ids=[7, 9], corners=f32(2, 4, 2),
                                  quality=f32(2), side_m=f32(2))
    assert detections.ids.dtype == np.int32
    assert detections.ids.tolist() == [7, 9]


def test_marker_corners_refuse_a_wrong_shape():
    with pytest.raises(ValidationError, match=r"shape \(2, 3, 2\) does not fit \(N, 4, 2\)"):
        MarkerDetections(header=HEADER, dictionary="", ids=np.arange(2, dtype=np.int32), corners=f32(2, 3, 2),
                         quality=f32(2), side_m=f32(2))


def test_blobs_refuse_mismatched_rows():
    with pytest.raises(ValidationError, match="same number of rows"):
        blobs(3, 2)


@pytest.mark.parametrize("descriptors", [np.zeros((2, 32), np.uint8), f32(2, 128), f32(2, 0)])
def test_keypoints_take_binary_float_or_no_descriptors(descriptors: np.ndarray):
    keypoints = Keypoints(header=HEADER, points=f32(2, 2), sizes=f32(2), angles=f32(2), responses=f32(2),
                          descriptors=descriptors)
    assert keypoints.descriptors.dtype == descriptors.dtype


@pytest.mark.parametrize(("descriptors", "norm"), [(np.zeros((2, 32), np.uint8), "hamming"), (f32(2, 128), "l2"),
                                                   (f32(2, 0), "")])
def test_keypoints_say_how_their_descriptors_compare(descriptors: np.ndarray, norm: str):
    keypoints = Keypoints(header=HEADER, points=f32(2, 2), sizes=f32(2), angles=f32(2), responses=f32(2),
                          descriptors=descriptors)
    assert keypoints.norm == norm


def test_keypoints_of_version_1_without_a_method_still_decode():
    keypoints = Keypoints(header=HEADER, method="orb", descriptor_type="ORB", points=f32(2, 2), sizes=f32(2),
                          angles=f32(2), responses=f32(2), descriptors=np.arange(64, dtype=np.uint8).reshape(2, 32))
    payload = encode(keypoints)
    field = b'"method":"orb",'
    assert payload.count(field) == 1
    old = payload.replace(b'"version":2', b'"version":1', 1).replace(field, b" " * len(field))
    decoded = decode(old)
    assert decoded.method == "" and decoded == keypoints.model_copy(update={"method": ""})
    with pytest.raises(DecodeError, match="version 3 is not understood"):
        decode(payload.replace(b'"version":2', b'"version":3', 1))


def test_keypoints_refuse_mismatched_descriptor_rows():
    with pytest.raises(ValidationError, match="same number of rows"):
        Keypoints(header=HEADER, points=f32(2, 2), sizes=f32(2), angles=f32(2), responses=f32(2),
                  descriptors=np.zeros((3, 32), np.uint8))


@pytest.mark.parametrize(
    ("ids", "colors", "valid"), [(4, 4, True), (4, 0, True), (3, 4, False), (4, 2, False)]
)
def test_point_cloud_needs_an_id_per_point_and_a_colour_per_point_or_none(ids: int, colors: int, valid: bool):
    def build() -> PointCloud:
        return PointCloud(header=HEADER, points=f32(4, 3), ids=np.arange(ids),
                          colors=np.zeros((colors, 3), np.uint8))

    if valid:
        assert len(build().points) == 4
    else:
        with pytest.raises(ValidationError, match="4 points need as many ids"):
            build()


def test_keyframes_need_a_stamp_and_a_pose_per_id_and_rigid_poses():
    poses = np.tile(np.eye(4), (3, 1, 1))
    poses[:, :3, 3] = np.arange(9.0).reshape(3, 3)
    keyframes = Keyframes(header=HEADER.model_copy(update={"frame_id": "map"}), child_frame_id="cam0",
                          ids=np.array([0, 4, 9]), stamps_ns=np.array([1, 5, 10]), poses=poses)
    again = decode(encode(keyframes))
    assert again == keyframes and again.poses.shape == (3, 4, 4) and again.ids.dtype == np.int64
    with pytest.raises(ValidationError, match="3 keyframe ids need as many stamps .got 2. and poses .got 3."):
        Keyframes(header=HEADER, child_frame_id="cam0", ids=np.arange(3), stamps_ns=np.arange(2), poses=poses)
    skewed = poses.copy()
    skewed[1, 3, 0] = 0.5
    with pytest.raises(ValidationError, match="last row 0 0 0 1"):
        Keyframes(header=HEADER, child_frame_id="cam0", ids=np.arange(3), stamps_ns=np.arange(3), poses=skewed)
    with pytest.raises(ValidationError, match="dtype float32"):
        Keyframes(header=HEADER, child_frame_id="cam0", ids=np.arange(3), stamps_ns=np.arange(3),
                  poses=poses.astype(np.float32))


def test_stage_timings_travel_as_json_and_refuse_a_negative_or_infinite_time():
    timings = StageTimings(header=HEADER, stages_ms={"keypoints": 4.5, "total": 9.0})
    assert decode(encode(timings)) == timings and encode(timings).startswith(b"{")
    with pytest.raises(ValidationError, match="stage 'match' took a negative time"):
        StageTimings(header=HEADER, stages_ms={"match": -1.0})
    with pytest.raises(ValidationError, match="finite"):
        StageTimings(header=HEADER, stages_ms={"match": math.inf})


# --- JSON views ---


def test_to_json_lists_arrays_and_names_schema_and_version():
    image = Image(header=HEADER, encoding="mono8", data=np.arange(6, dtype=np.uint8).reshape(2, 3))
    view = to_json(image)
    assert list(view)[:2] == ["schema", "version"]
    assert view == {"schema": "artrack.Image", "version": 1, "encoding": "mono8",
                    "header": {"stamp_ns": 1_700_000_000_000_000_000, "frame_id": "cam0", "seq": 3},
                    "data": [[0, 1, 2], [3, 4, 5]]}


@pytest.mark.parametrize(("limit", "summarised"), [(None, False), (6, False), (5, True), (0, True)])
def test_to_json_summarises_arrays_larger_than_the_limit(limit: int | None, summarised: bool):
    image = Image(header=HEADER, encoding="mono8", data=np.zeros((2, 3), np.uint8))
    data = to_json(image, max_array_elements=limit)["data"]
    assert data == ({"dtype": "uint8", "shape": [2, 3]} if summarised else [[0, 0, 0], [0, 0, 0]])


def test_to_json_summarises_each_array_on_its_own():
    cloud = PointCloud(header=HEADER, points=f32(4, 3), ids=np.arange(4), colors=np.zeros((0, 3), np.uint8))
    view = to_json(cloud, max_array_elements=4)
    assert view["points"] == {"dtype": "float32", "shape": [4, 3]}
    assert view["ids"] == [0, 1, 2, 3]
    assert view["colors"] == []


def test_to_json_writes_enums_as_their_values():
    assert to_json(Pose(header=HEADER, child_frame_id="marker/7"))["state"] == "tracking"


CARD = ((-0.04, 0.03, 0.0), (0.04, 0.03, 0.0), (0.04, -0.03, 0.0), (-0.04, -0.03, 0.0))
"""An 8 x 6 cm card's corners, top-left first, in artrack's target frame (origin at the centre, y up)."""


def card(corners=CARD, width_m: float = 0.08, height_m: float = 0.06, name: str = "card") -> ImageTarget:
    return ImageTarget(name=name, frame_id=f"target/{name}", width_m=width_m, height_m=height_m, corners=corners)


def test_an_image_target_whose_corners_span_its_size_in_any_frame_is_valid():
    assert card().corners == CARD
    top_left_origin_y_down = ((0.0, 0.0, 0.0), (0.08, 0.0, 0.0), (0.08, 0.06, 0.0), (0.0, 0.06, 0.0))
    assert card(top_left_origin_y_down).corners[2] == (0.08, 0.06, 0.0)
    tilted = ((0.0, 0.0, 0.0), (0.0, 0.0, 0.08), (0.0, -0.06, 0.08), (0.0, -0.06, 0.0))
    assert card(tilted).width_m == 0.08
    described = ImageTargets(header=HEADER, targets=(card(), card(name="poster")))
    assert decode(encode(described)) == described


@pytest.mark.parametrize(("corners", "width_m", "height_m", "why"), [
    (CARD, 0.09, 0.06, "span 0.08 x 0.06 m, not its 0.09 x 0.06 m"),
    (CARD, 0.08, 0.05, "span 0.08 x 0.06 m"),
    (((-0.04, 0.03, 0.0), (0.04, 0.03, 0.0), (0.05, -0.03, 0.0), (-0.04, -0.03, 0.0)), 0.08, 0.06, "rectangle"),
    (((0.0, 0.0, 0.0), (0.08, 0.0, 0.0), (0.08 + 0.036, 0.048, 0.0), (0.036, 0.048, 0.0)), 0.08, 0.06, "rectangle"),
])
def test_an_image_target_whose_corners_do_not_make_its_rectangle_is_refused(corners, width_m, height_m, why):
    with pytest.raises(ValidationError, match=why):
        card(corners, width_m, height_m)


def test_image_targets_of_one_name_twice_are_refused():
    with pytest.raises(ValidationError, match="'card' is described more than once"):
        ImageTargets(header=HEADER, targets=(card(), card()))
