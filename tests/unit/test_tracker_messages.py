"""The per-frame messages of the marker and image-target trackers: built with as little work as they
need, and equal, to the byte once encoded, to the same messages built field by field and validated;
and the camera model a tracker makes of each frame's CameraInfo."""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np
import pytest
from pydantic import ValidationError

from protocol.codec import decode, encode
from protocol.detections import MarkerDetections
from protocol.keys import Keys
from protocol.message import Header, Message
from protocol.poses import Pose, PoseQuality
from protocol.sensors import Image
from protocol.targets import ImageTargets
from protocol.tracking_state import TrackingState
from services.convert import CameraModels, camera_info, camera_model, pose_message, transform_from_matrix
from services.detection.markers.detector import REFINEMENTS
from services.detection.markers.node import as_message
from services.detection.markers.settings import DetectorSettings
from services.estimation.markers import node as marker_node
from services.estimation.markers.pose import MarkerPoseEstimator, TargetPose
from services.estimation.targets import build_target
from services.estimation.targets import node as target_node
from services.estimation.targets.tracking import TargetPose as FoundTarget
from services.geometry.rotation import matrix_from_rotvec
from services.geometry.se3 import make_transform
from services.synthetic import make_scene

HEADER = Header(stamp_ns=1_700_000_000_000_000_000, frame_id="cam0", seq=42)
FRAMES = range(0, 600, 40)


class Sent:
    """A publisher that keeps what it is given; ``subscribed`` is what ``matched`` answers."""

    def __init__(self, subscribed: bool = True):
        self.messages: list[Message] = []
        self.subscribed = subscribed

    def put(self, message: Message) -> None:
        self.messages.append(message)

    def matched(self) -> bool:
        return self.subscribed


class Bench:
    """What a tracker node's per-frame helpers use of a ``Node``: its keys, publishers (kept by key) and reports."""

    def __init__(self, subscribed: bool = True):
        self.keys = Keys()
        self.out: dict[str, Sent] = {}
        self.reports: list[tuple[Any, ...]] = []
        self.answers: dict[str, Any] = {}
        self.subscribed = subscribed

    def publisher(self, key: str, cls: type[Message], role: Any = None) -> Sent:
        return self.out.setdefault(key, Sent(self.subscribed))

    def report(self, *args: Any) -> None:
        self.reports.append(args)

    def answer(self, key: str, reply: Any) -> None:
        self.answers[key] = reply


def validated_pose(header: Header, child: str, T: np.ndarray, state: TrackingState = TrackingState.TRACKING,
                   rms_px: float | None = None, inliers: int = 0, ambiguous: bool = False,
                   covariance: np.ndarray | None = None, residual_rms_m: float | None = None) -> Pose:
    """The pose built part by part, each part validated on its own."""
    return Pose(header=header, child_frame_id=child, state=state, transform=transform_from_matrix(T),
                quality=PoseQuality(reprojection_rms_px=rms_px, residual_rms_m=residual_rms_m, inliers=inliers,
                                    ambiguous=ambiguous),
                covariance=None if covariance is None else tuple(float(v) for v in np.ravel(covariance)))


def assert_same(built: Message, reference: Message) -> None:
    assert built == reference
    assert encode(built) == encode(reference)
    assert decode(encode(built)) == reference


def rotations() -> list[np.ndarray]:
    """Random rotations and the half turns, where each branch of Shepperd's method is taken."""
    rng = np.random.default_rng(3)
    turns = [matrix_from_rotvec(v) for v in rng.normal(size=(40, 3))]
    half = [matrix_from_rotvec(math.pi * axis) for axis in np.eye(3)]
    return [np.eye(3), *turns, *half, matrix_from_rotvec([1e-9, 0.0, 0.0])]


def test_a_pose_message_is_the_pose_built_part_by_part():
    rng = np.random.default_rng(5)
    for n, R in enumerate(rotations()):
        T = make_transform(R, rng.normal(size=3))
        A = rng.normal(size=(6, 6))
        covariance = A @ A.T * 1e-6
        kwargs = {"state": (TrackingState.TRACKING, TrackingState.RECOGNISED)[n % 2], "rms_px": float(rng.random()),
                  "inliers": n, "ambiguous": bool(n % 3 == 0), "covariance": covariance,
                  "residual_rms_m": (None, float(rng.random()) * 1e-3)[n % 2]}
        child = f"marker/{n}"
        assert_same(pose_message(HEADER, child, T, **kwargs), validated_pose(HEADER, child, T, **kwargs))
    bare = make_transform(rotations()[5], [0.1, -0.2, 0.7])
    assert_same(pose_message(HEADER, "target/a", bare), validated_pose(HEADER, "target/a", bare))


@pytest.mark.parametrize("change", [
    {"T": make_transform(np.eye(3), [0.0, math.nan, 1.0])},
    {"covariance": np.full((6, 6), math.inf)},
    {"covariance": np.eye(5)},
    {"rms_px": -1.0},
    {"residual_rms_m": -1e-3},
])
def test_a_pose_message_refuses_what_the_protocol_refuses(change):
    args: dict[str, Any] = {"T": np.eye(4), "rms_px": 0.2, "covariance": np.eye(6), **change}
    T = args.pop("T")
    for build in (pose_message, validated_pose):
        with pytest.raises(ValidationError):
            build(HEADER, "marker/1", T, **args)


def scene_frames() -> tuple[list[np.ndarray], Any]:
    scene = make_scene("markers")
    camera = scene.cameras[0]
    return [scene.render(i).images[camera.name] for i in FRAMES], camera


@pytest.mark.parametrize("refinement", sorted(REFINEMENTS))
def test_a_frames_detections_are_the_validated_message(refinement):
    frames, camera = scene_frames()
    detector = DetectorSettings(marker_length=0.05, lengths={3: 0.08}, refinement=refinement).detector()
    found = [detector.detect(frame, camera.K, camera.dist) for frame in frames]
    found.append(detector.detect(np.zeros((480, 640), np.uint8)))
    assert sum(map(len, found)) > 3 * len(frames) and len(found[-1]) == 0
    for n, markers in enumerate(found):
        header = HEADER.model_copy(update={"seq": n})
        built = as_message(header, "DICT_4X4_50", markers)
        reference = MarkerDetections(header=header, dictionary="DICT_4X4_50", ids=markers.ids,
                                     corners=markers.corners, quality=markers.quality, side_m=markers.side_m)
        assert_same(built, reference)
        assert all(getattr(built, name).dtype == getattr(reference, name).dtype for name in built.ARRAY_FIELDS)


def test_the_marker_node_publishes_each_estimate_as_its_validated_pose():
    frames, camera = scene_frames()
    detector = DetectorSettings(marker_length=0.05).detector()
    node, mine, theirs = Bench(), MarkerPoseEstimator(), MarkerPoseEstimator()
    publishers = marker_node.PosePublishers(node, "cam0")
    expected: list[Pose] = []
    tracked: set[str] = set()
    for n, frame in enumerate(frames[:6] + frames[9:]):  # a gap: markers of frames 6 to 8 are lost
        header = HEADER.model_copy(update={"seq": n})
        detections = as_message(header, "DICT_4X4_50", detector.detect(frame, camera.K, camera.dist))
        marker_node._estimate(node, detections, camera, mine, publishers)
        estimate = theirs.estimate(detections.ids, detections.corners, detections.side_m, camera.K, camera.dist)
        posed: list[TargetPose] = estimate.poses
        expected += [validated_pose(header, p.target, p.T, rms_px=p.rms_px, inliers=p.points, ambiguous=p.ambiguous,
                                    covariance=p.covariance) for p in posed]
        now = {p.target for p in posed}
        expected += [Pose(header=header, child_frame_id=child, state=TrackingState.LOST)
                     for child in sorted(tracked - now)]
        tracked = now
    sent = [message for key in sorted(node.out) for message in node.out[key].messages]
    assert len(sent) == len(expected) > 40
    assert any(pose.state is TrackingState.LOST for pose in expected)
    by_key = sorted(expected, key=lambda pose: (node.keys.pose(f"cam0/{pose.child_frame_id}"), pose.header.seq))
    for built, reference in zip(sent, by_key, strict=True):
        assert_same(built, reference)


@pytest.mark.parametrize("found", [
    FoundTarget(TrackingState.TRACKING, "poster", "", make_transform(matrix_from_rotvec([0.2, -0.1, 3.0]), [0, 0, 1]),
                120, 0.31, np.diag(np.arange(1.0, 7.0)) * 1e-6),
    FoundTarget(TrackingState.RECOGNISED, "poster", "", make_transform(rotations()[-2], [0.1, 0.2, 0.9]), 40,
                math.nan, np.full((6, 6), math.nan)),
    FoundTarget(TrackingState.TRACKING, "poster", "", make_transform(rotations()[7], [0.1, 0.2, 0.9]), 30, 0.5, None),
    FoundTarget(TrackingState.LOST, "poster", "too_few_matches"),
])
def test_a_targets_pose_is_its_validated_pose(found):
    if found.T_camera_target is None:
        reference = Pose(header=HEADER, child_frame_id="target/poster", state=TrackingState.LOST, reason=found.reason)
    else:
        finite = found.covariance is not None and bool(np.all(np.isfinite(found.covariance)))
        reference = validated_pose(HEADER, "target/poster", found.T_camera_target, found.state,
                                   found.rms_px if math.isfinite(found.rms_px) else None, found.inliers,
                                   covariance=found.covariance if finite else None)
    assert_same(target_node.as_pose(HEADER, found), reference)


def test_the_targets_are_answered_from_the_start_and_published_once_before_the_first_poses():
    texture = np.random.default_rng(3).integers(0, 256, (120, 160), np.uint8)
    targets = [build_target("poster", texture, 0.32), build_target("card", texture[:, :90], 0.09)]
    bench = Bench()
    descriptions = target_node._Descriptions(bench, "cam0", targets)
    key = Keys().targets("cam0")
    early = bench.answers[key]()
    assert isinstance(early, ImageTargets) and early.header.frame_id == "cam0" and not bench.out[key].messages
    for seq in range(3):
        descriptions.publish(HEADER.model_copy(update={"seq": HEADER.seq + seq}))
    (sent,) = bench.out[key].messages
    assert sent.header == HEADER and bench.answers[key]() == sent
    for target, described in zip(targets, sent.targets, strict=True):
        assert (described.name, described.frame_id) == (target.name, f"target/{target.name}")
        assert (described.width_m, described.height_m) == (target.width_m, target.height_m)
        w, h = target.width_m / 2, target.height_m / 2
        np.testing.assert_allclose(described.corners, [[-w, h, 0], [w, h, 0], [w, -h, 0], [-w, -h, 0]])
    assert sent.targets[1].height_m == pytest.approx(0.09 * 120 / 90)


@pytest.mark.parametrize("subscribed", [False, True])
def test_an_overlay_is_drawn_only_for_a_subscriber(subscribed):
    frames, camera = scene_frames()
    image = Image(header=HEADER, encoding="mono8", data=frames[0])
    markers = Bench(subscribed)
    overlay = marker_node._Overlay(markers, "cam0", None)
    detections = as_message(HEADER, "DICT_4X4_50", DetectorSettings(marker_length=0.05).detector().detect(frames[0]))
    overlay.put(image, detections, camera, MarkerPoseEstimator().estimate(
        detections.ids, detections.corners, detections.side_m, camera.K, camera.dist))
    targets = Bench(subscribed)
    target_node._Overlay(targets, "cam0", []).put(image, camera.K, camera.dist, [])
    sent = [next(iter(bench.out.values())).messages for bench in (markers, targets)]
    assert [len(messages) for messages in sent] == [int(subscribed)] * 2
    if subscribed:
        drawn = [messages[0] for messages in sent]
        assert all(isinstance(m, Image) and m.encoding == "bgr8" and m.header.frame_id == "cam0/overlay" for m in drawn)
        assert not np.array_equal(drawn[0].data, drawn[1].data)


def test_a_camera_info_that_says_the_same_gives_the_same_model():
    _, camera = scene_frames()
    models = CameraModels()
    infos = [camera_info(HEADER.model_copy(update={"seq": n}), camera) for n in range(3)]
    moved = dataclasses.replace(camera, K=camera.K * [[1.01], [1.01], [1.0]])
    shifted = transform_from_matrix(make_transform(np.eye(3), [0.1, 0.0, 0.0]))
    infos += [camera_info(HEADER.model_copy(update={"seq": 3}), moved), infos[0],
              infos[0].model_copy(update={"header": HEADER.model_copy(update={"frame_id": "cam1"})}),
              infos[0].model_copy(update={"T_rig_camera": shifted}),
              infos[0].model_copy(update={"d": (0.0, 0.0, 0.0, 0.0)})]
    made = [models(info) for info in infos]
    for model, info in zip(made, infos, strict=True):
        reference = camera_model(info)
        assert model.name == reference.name and (model.width, model.height) == (reference.width, reference.height)
        for name in ("K", "dist", "T_rig_camera"):
            assert np.array_equal(getattr(model, name), getattr(reference, name))
    assert made[1] is made[0] and made[2] is made[0]
    assert len({id(model) for model in made}) == len(made) - 2
    with pytest.raises(ValueError, match="plumb_bob only"):
        models(infos[0].model_copy(update={"distortion_model": "equidistant"}))
    named = CameraModels("left")
    assert named(infos[5]).name == "left" and named(infos[0]).name == "left"
