"""Hypothesis strategies that build a valid instance of every registered message type.

``MESSAGES`` maps each schema name to its strategy; ``test_codec`` fails when a registered
schema has none, so a new message type must be added here.
"""

from __future__ import annotations

import math

import hypothesis.extra.numpy as hnp
import numpy as np
from hypothesis import strategies as st

from protocol import (
    Blobs,
    CameraInfo,
    ClientState,
    ConfigAnswer,
    ConfigChange,
    ErrorReport,
    FlowAck,
    FlowEnd,
    FrameTransform,
    GroundTruth,
    Header,
    Image,
    ImageTarget,
    ImageTargets,
    Keyframes,
    Keypoints,
    MarkerDetections,
    NodeStats,
    PipelineHealth,
    PointCloud,
    Points3D,
    Pose,
    PoseQuality,
    RegionOfInterest,
    ReplayCommand,
    ReplayControl,
    ReplayStatus,
    RigidBodies,
    RigidBody,
    StageTimings,
    StaticTransforms,
    StreamStats,
    Subscription,
    SupervisedNode,
    SyncInputStats,
    SyncStats,
    TrackingState,
    Trajectory,
    Transform,
)

texts = st.text(max_size=12)  # any unicode, surrogates excepted (they cannot be UTF-8 encoded)
big_counts = st.integers(min_value=0, max_value=2**80)
finite = st.floats(allow_nan=False, allow_infinity=False)
non_negative = st.floats(min_value=0, allow_nan=False, allow_infinity=False)
positive = st.floats(min_value=1e-9, max_value=1e9)
rows = st.integers(min_value=0, max_value=5)
sides = st.integers(min_value=0, max_value=7)

headers = st.builds(Header, stamp_ns=big_counts, frame_id=texts, seq=big_counts)


def arrays(dtype: str, shape: tuple[int, ...]) -> st.SearchStrategy[np.ndarray]:
    """Arrays of ``dtype`` in either byte order, C or Fortran layout; floats without NaN.

    NaN is left out because ``Message.__eq__`` compares values; ``test_codec`` checks NaN bits separately.
    """
    base = np.dtype(dtype)
    orders = st.sampled_from(["<", ">"]) if base.itemsize > 1 else st.just("|")
    elements = hnp.from_dtype(base, allow_nan=False) if base.kind == "f" else hnp.from_dtype(base)
    layouts = st.sampled_from([np.ascontiguousarray, np.asfortranarray])
    return st.builds(
        lambda order, layout, values: layout(values.astype(base.newbyteorder(order))),
        orders,
        layouts,
        hnp.arrays(base, shape, elements=elements),
    )


@st.composite
def quaternions(draw: st.DrawFn) -> tuple[float, float, float, float]:
    """Unit quaternions, scaled by up to 5e-4 off unit norm (Transform normalises them)."""
    q = draw(st.tuples(*[st.floats(-1, 1)] * 4).filter(lambda v: math.hypot(*v) > 0.1))
    scale = draw(st.floats(1 - 5e-4, 1 + 5e-4)) / math.hypot(*q)
    return tuple(v * scale for v in q)


transforms = st.builds(Transform, translation=st.tuples(finite, finite, finite), rotation=quaternions())
qualities = st.builds(PoseQuality, reprojection_rms_px=st.none() | non_negative, inliers=big_counts,
                      ambiguous=st.booleans(), residual_rms_m=st.none() | non_negative)
states = st.sampled_from(TrackingState)

IMAGE_LAYOUT = {"mono8": ("uint8", 1), "mono16": ("uint16", 1), "bgr8": ("uint8", 3), "bgra8": ("uint8", 4)}
DISTORTION_COUNTS = {"plumb_bob": (0, 4, 5), "rational_polynomial": (8,), "equidistant": (4,)}


@st.composite
def images(draw: st.DrawFn) -> Image:
    encoding = draw(st.sampled_from(sorted(IMAGE_LAYOUT)))
    dtype, channels = IMAGE_LAYOUT[encoding]
    shape = (draw(sides), draw(sides)) + ((channels,) if channels > 1 else ())
    return Image(header=draw(headers), encoding=encoding, data=draw(arrays(dtype, shape)))


@st.composite
def camera_infos(draw: st.DrawFn) -> CameraInfo:
    model = draw(st.sampled_from(sorted(DISTORTION_COUNTS)))
    d = draw(st.sampled_from(DISTORTION_COUNTS[model]).flatmap(lambda n: st.tuples(*[finite] * n)))
    fx, fy, cx, cy, skew = draw(positive), draw(positive), draw(finite), draw(finite), draw(finite)
    return CameraInfo(
        header=draw(headers),
        width=draw(st.integers(1, 2**31)),
        height=draw(st.integers(1, 2**31)),
        distortion_model=model,
        d=d,
        k=(fx, skew, cx, 0.0, fy, cy, 0.0, 0.0, 1.0),
        r=draw(st.tuples(*[finite] * 9)),
        p=draw(st.none() | st.tuples(*[finite] * 12)),
        binning_x=draw(big_counts),
        binning_y=draw(big_counts),
        roi=draw(st.builds(RegionOfInterest, x_offset=big_counts, y_offset=big_counts, height=big_counts,
                           width=big_counts, do_rectify=st.booleans())),
        T_rig_camera=draw(transforms),
    )


@st.composite
def marker_detections(draw: st.DrawFn) -> MarkerDetections:
    n = draw(rows)
    return MarkerDetections(header=draw(headers), dictionary=draw(texts), ids=draw(arrays("int32", (n,))),
                            corners=draw(arrays("float32", (n, 4, 2))), quality=draw(arrays("float32", (n,))),
                            side_m=draw(arrays("float32", (n,))))


@st.composite
def keypoints(draw: st.DrawFn) -> Keypoints:
    n, width = draw(rows), draw(st.sampled_from([0, 1, 32, 128]))
    descriptor_dtype = draw(st.sampled_from(["uint8", "float32"]))
    return Keypoints(header=draw(headers), method=draw(texts), descriptor_type=draw(texts),
                     points=draw(arrays("float32", (n, 2))), sizes=draw(arrays("float32", (n,))),
                     angles=draw(arrays("float32", (n,))), responses=draw(arrays("float32", (n,))),
                     descriptors=draw(arrays(descriptor_dtype, (n, width))))


@st.composite
def point_clouds(draw: st.DrawFn) -> PointCloud:
    n = draw(rows)
    colored = draw(st.sampled_from([0, n]))
    return PointCloud(header=draw(headers), points=draw(arrays("float32", (n, 3))),
                      ids=draw(arrays("int64", (n,))), colors=draw(arrays("uint8", (colored, 3))))


def _rigid_poses(draw: st.DrawFn, n: int) -> np.ndarray:
    poses = draw(arrays("float64", (n, 4, 4)))
    poses[:, 3] = (0.0, 0.0, 0.0, 1.0)
    return poses


@st.composite
def keyframe_sets(draw: st.DrawFn) -> Keyframes:
    n = draw(rows)
    return Keyframes(header=draw(headers), child_frame_id=draw(texts), ids=draw(arrays("int64", (n,))),
                     stamps_ns=draw(arrays("int64", (n,))), poses=_rigid_poses(draw, n))


@st.composite
def trajectories(draw: st.DrawFn) -> Trajectory:
    n = draw(rows)
    return Trajectory(header=draw(headers), child_frame_id=draw(texts), stamps_ns=draw(arrays("int64", (n,))),
                      seqs=draw(arrays("int64", (n,))), poses=_rigid_poses(draw, n))


@st.composite
def blobs(draw: st.DrawFn) -> Blobs:
    n = draw(rows)
    return Blobs(header=draw(headers), method=draw(st.sampled_from(["ir", "log", "colour"])),
                 centroids=draw(arrays("float64", (n, 2))), areas=draw(arrays("float32", (n,))),
                 radii=draw(arrays("float32", (n,))), quality=draw(arrays("float32", (n,))),
                 flags=draw(arrays("uint8", (n,))))


@st.composite
def points_3d(draw: st.DrawFn) -> Points3D:
    n, names = draw(rows), draw(_tuples_of(texts))
    body = draw(st.lists(st.integers(-1, len(names) - 1), min_size=n, max_size=n))
    return Points3D(header=draw(headers), bodies=names, points=draw(arrays("float64", (n, 3))),
                    residual_px=draw(arrays("float32", (n,))), views=draw(arrays("uint8", (n,))),
                    covariances=draw(arrays("float64", (n, 3, 3))), body=np.array(body, np.int32))


@st.composite
def image_targets(draw: st.DrawFn) -> ImageTargets:
    """Targets of sizes from a millimetre to a kilometre, their frames' origins at the image's centre or a corner."""
    sizes = st.floats(min_value=1e-3, max_value=1e3)
    names = draw(st.lists(texts.filter(bool), max_size=3, unique=True))
    described = []
    for name in names:
        w, h = draw(sizes), draw(sizes)
        x0, y0 = draw(st.sampled_from([(-w / 2, h / 2), (0.0, 0.0), (0.0, h)]))
        described.append(ImageTarget(name=name, frame_id=f"target/{name}", width_m=w, height_m=h, corners=(
            (x0, y0, 0.0), (x0 + w, y0, 0.0), (x0 + w, y0 - h, 0.0), (x0, y0 - h, 0.0))))
    return ImageTargets(header=draw(headers), targets=tuple(described))


def _tuples_of(strategy: st.SearchStrategy) -> st.SearchStrategy[tuple]:
    return st.lists(strategy, max_size=3).map(tuple)


directions = st.sampled_from(["in", "out"])
stream_stats = st.builds(StreamStats, key=texts, direction=directions, messages=big_counts,
                         dropped=big_counts, missing=big_counts, decode_errors=big_counts, rate_hz=non_negative)
sync_stats = st.builds(
    SyncStats, by=st.sampled_from(["seq", "stamp"]), tolerance_ns=big_counts, sets=big_counts, dropped=big_counts,
    resets=big_counts, inputs=_tuples_of(st.builds(
        SyncInputStats, name=texts, key=texts, received=big_counts, joined=big_counts, evicted=big_counts,
        superseded=big_counts, out_of_order=big_counts)))

MESSAGES: dict[str, st.SearchStrategy] = {
    "artrack.Image": images(),
    "artrack.CameraInfo": camera_infos(),
    "artrack.MarkerDetections": marker_detections(),
    "artrack.Keypoints": keypoints(),
    "artrack.PointCloud": point_clouds(),
    "artrack.Keyframes": keyframe_sets(),
    "artrack.Trajectory": trajectories(),
    "artrack.Blobs": blobs(),
    "artrack.Points3D": points_3d(),
    "artrack.Pose": st.builds(Pose, header=headers, child_frame_id=texts, transform=transforms, state=states,
                              quality=qualities, covariance=st.none() | st.tuples(*[finite] * 36)),
    "artrack.RigidBodies": st.builds(RigidBodies, header=headers, bodies=_tuples_of(
        st.builds(RigidBody, name=texts, transform=transforms, state=states, quality=qualities))),
    "artrack.GroundTruth": st.builds(GroundTruth, header=headers, transforms=_tuples_of(
        st.builds(FrameTransform, parent_frame=texts, child_frame=texts, transform=transforms))),
    "artrack.ImageTargets": image_targets(),
    "artrack.StaticTransforms": st.builds(StaticTransforms, header=headers, transforms=st.lists(
        st.builds(FrameTransform, parent_frame=texts.filter(bool), child_frame=texts.filter(bool),
                  transform=transforms).filter(lambda edge: edge.parent_frame != edge.child_frame),
        max_size=3, unique_by=lambda edge: frozenset((edge.parent_frame, edge.child_frame))).map(tuple)),
    "artrack.NodeStats": st.builds(
        NodeStats, header=headers, node=texts, kind=texts, host=texts, pid=st.integers(-(2**70), 2**70),
        state=st.sampled_from(["starting", "running", "stopping"]), uptime_s=non_negative,
        received=big_counts, published=big_counts, processed=big_counts, dropped=big_counts,
        missing=big_counts, decode_errors=big_counts, ended=st.booleans(),
        processing_ms_p50=st.none() | finite, processing_ms_p99=st.none() | finite,
        latency_ms_p50=st.none() | finite, latency_ms_p99=st.none() | finite,
        streams=_tuples_of(stream_stats), synced=_tuples_of(sync_stats)),
    "artrack.ClientState": st.builds(
        ClientState, header=headers, client=texts, app=texts, host=texts, pid=st.integers(-(2**70), 2**70),
        uptime_s=non_negative, subscriptions=_tuples_of(st.builds(
            Subscription, key=texts, received=big_counts, dropped=big_counts, decode_errors=big_counts,
            last_stamp_ns=st.none() | st.integers(0, 2**63)))),
    "artrack.PipelineHealth": st.builds(
        PipelineHealth, header=headers, pipeline=texts, host=texts, pid=st.integers(-(2**70), 2**70),
        uptime_s=non_negative, nodes=_tuples_of(st.builds(
            SupervisedNode, name=texts, kind=texts,
            state=st.sampled_from(["running", "backing_off", "failed", "finished"]),
            pid=st.none() | st.integers(0, 2**31), uptime_s=non_negative, restarts=big_counts,
            exit_code=st.none() | st.integers(-64, 255)))),
    "artrack.ConfigChange": st.builds(ConfigChange, header=headers, values=st.dictionaries(texts, texts, max_size=3)),
    "artrack.ConfigAnswer": st.builds(
        ConfigAnswer, header=headers, node=texts, applied=st.dictionaries(texts, texts, max_size=3),
        refused=st.dictionaries(texts, texts, max_size=3), params=st.dictionaries(texts, texts, max_size=3)),
    "artrack.FlowAck": st.builds(FlowAck, header=headers, node=texts, seq=st.integers(-1, 2**63),
                                 started_ns=big_counts),
    "artrack.FlowEnd": st.builds(FlowEnd, header=headers, node=texts, last_seq=st.integers(-1, 2**63),
                                 frames=big_counts, published=st.dictionaries(texts, big_counts, max_size=3)),
    "artrack.ErrorReport": st.builds(ErrorReport, header=headers, node=texts, kind=texts, detail=texts,
                                     key=texts, count=st.integers(1, 2**80)),
    "artrack.StageTimings": st.builds(StageTimings, header=headers,
                                      stages_ms=st.dictionaries(texts, non_negative, max_size=4)),
    "artrack.ReplayControl": st.builds(ReplayControl, header=headers, command=st.sampled_from(ReplayCommand)),
    "artrack.ReplayStatus": st.builds(
        ReplayStatus, header=headers, node=texts, path=texts, state=st.sampled_from(["playing", "paused", "stopped"]),
        played=big_counts, passes=big_counts, position_s=non_negative, rate=positive),
}
"""One strategy per registered schema name."""
