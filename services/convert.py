"""Between wire messages and the arrays the algorithms use.

Nodes call these at their edges: a ``protocol.Transform`` becomes a (4, 4) ``T_a_b``
matrix and back, a ``CameraInfo`` becomes a ``CameraModel`` (K, distortion, pose in rig)
and back, ``StaticTransforms`` become a ``FrameGraph`` and back. Nothing else in artrack
converts between the two by hand.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from protocol.message import Header
from protocol.poses import Pose
from protocol.sensors import CameraInfo
from protocol.spatial import RIG_FRAME, FrameTransform, StaticTransforms, Transform
from protocol.tracking_state import TrackingState
from services.geometry.camera import CameraModel
from services.geometry.frames import FrameGraph
from services.geometry.rotation import quaternion_of_rows
from services.geometry.se3 import from_quaternion_translation, invert, to_quaternion_translation
from services.geometry.transform_tree import TransformTree


def matrix_from_transform(transform: Transform) -> np.ndarray:
    """(4, 4) float64 ``T_parent_child`` of a wire transform."""
    return from_quaternion_translation(np.array(transform.rotation), np.array(transform.translation))


def transform_from_matrix(T: np.ndarray) -> Transform:
    """Wire transform of a (4, 4) rigid ``T_parent_child``."""
    q, t = to_quaternion_translation(np.asarray(T, dtype=np.float64))
    return Transform(translation=tuple(float(v) for v in t), rotation=tuple(float(v) for v in q))


def in_tree(tree: TransformTree, edges: Iterable[FrameTransform]) -> list[FrameTransform]:
    """``edges`` (``T_parent_child`` each) as they join ``tree`` (``TransformTree.edge``, which keeps them): named
    as the tree says, a turned-round edge carrying the inverse transform ``T_child_parent``."""
    placed = []
    for edge in edges:
        parent, child, inverted = tree.edge(edge.parent_frame, edge.child_frame)
        transform = transform_from_matrix(invert(matrix_from_transform(edge.transform))) if inverted else edge.transform
        placed.append(FrameTransform(parent_frame=parent, child_frame=child, transform=transform))
    return placed


def pose_message(header: Header, child: str, T: np.ndarray, *, state: TrackingState = TrackingState.TRACKING,
                 rms_px: float | None = None, inliers: int = 0, ambiguous: bool = False,
                 covariance: np.ndarray | None = None, residual_rms_m: float | None = None) -> Pose:
    """The ``Pose`` of a (4, 4) float64 rigid ``T_<header.frame_id>_<child>`` with its quality and (6, 6)
    ``covariance`` (None: none), as a tracker publishes it.

    Built in one validation pass from plain Python values (the transform's rows taken out of numpy once),
    rather than the transform and the quality validated as models of their own first: a tracker node
    makes one for every pose of every frame. The result equals
    ``Pose(header=header, child_frame_id=child, state=state, transform=transform_from_matrix(T),
    quality=PoseQuality(reprojection_rms_px=rms_px, residual_rms_m=residual_rms_m, inliers=inliers,
    ambiguous=ambiguous), covariance=...)``;
    values the protocol refuses (a non-finite translation or covariance, a negative RMS) raise as there.
    """
    rows = np.asarray(T, dtype=np.float64).tolist()
    return Pose.model_validate({
        "header": header, "child_frame_id": child, "state": state,
        "transform": {"translation": (rows[0][3], rows[1][3], rows[2][3]), "rotation": quaternion_of_rows(rows)},
        "quality": {"reprojection_rms_px": rms_px, "residual_rms_m": residual_rms_m, "inliers": inliers,
                    "ambiguous": ambiguous},
        "covariance": None if covariance is None else np.asarray(covariance, dtype=np.float64).ravel().tolist(),
    })


def frame_transforms(truth: list[tuple[str, str, np.ndarray]]) -> tuple[FrameTransform, ...]:
    """Wire form of ``(parent_frame, child_frame, T_parent_child (4, 4))`` triples."""
    return tuple(FrameTransform(parent_frame=parent, child_frame=child, transform=transform_from_matrix(T))
                 for parent, child, T in truth)


def camera_info(header: Header, camera: CameraModel) -> CameraInfo:
    """CameraInfo (plumb_bob, ROS layout) of ``camera`` under ``header``."""
    K = np.asarray(camera.K, dtype=np.float64)
    P = np.hstack([K, np.zeros((3, 1))])
    return CameraInfo(header=header, width=camera.width, height=camera.height, distortion_model="plumb_bob",
                      d=tuple(float(v) for v in camera.dist), k=tuple(float(v) for v in K.ravel()),
                      p=tuple(float(v) for v in P.ravel()), T_rig_camera=transform_from_matrix(camera.T_rig_camera))


def camera_model(info: CameraInfo, name: str | None = None) -> CameraModel:
    """CameraModel of a plumb_bob CameraInfo (``name`` defaults to the header's frame id)."""
    if info.distortion_model != "plumb_bob":
        raise ValueError(f"distortion model {info.distortion_model} is not supported here (plumb_bob only)")
    dist = np.zeros(5)
    dist[: len(info.d)] = info.d
    return CameraModel(name=name or info.header.frame_id, width=info.width, height=info.height,
                       K=np.array(info.k, dtype=np.float64).reshape(3, 3), dist=dist,
                       T_rig_camera=matrix_from_transform(info.T_rig_camera))


class CameraModels:
    """``camera_model`` of one camera's CameraInfo stream, message after message.

    A capture node sends its CameraInfo with every frame, nearly always saying what the previous one
    said: one that does (same frame id, size, distortion, intrinsics and ``T_rig_camera``) gives back the
    model made for that one, so a frame pays a comparison of those fields rather than a new model.
    The model is shared: it is frozen, and its arrays are read, never written. ``name`` names the models
    (default: each CameraInfo's frame id).
    """

    def __init__(self, name: str | None = None) -> None:
        self.name = name
        self._said: tuple[object, ...] | None = None
        self._model: CameraModel | None = None

    def __call__(self, info: CameraInfo) -> CameraModel:
        said = (info.header.frame_id, info.width, info.height, info.distortion_model, info.d, info.k,
                info.T_rig_camera)
        if self._model is None or said != self._said:
            self._model = camera_model(info, self.name)
            self._said = said
        return self._model


def rig_static_transforms(header: Header, cameras: dict[str, CameraModel]) -> StaticTransforms:
    """Each camera's ``T_rig_camera``: ``RIG_FRAME`` the parent, the camera's name (the key) the child."""
    return StaticTransforms(header=header, transforms=frame_transforms(
        [(RIG_FRAME, name, camera.T_rig_camera) for name, camera in cameras.items()]))


def static_transforms(header: Header, graph: FrameGraph) -> StaticTransforms:
    """Wire form of the stored edges of ``graph``."""
    return StaticTransforms(header=header, transforms=frame_transforms(graph.edges()))


def frame_graph(messages: list[StaticTransforms], graph: FrameGraph | None = None) -> FrameGraph:
    """The edges of ``messages`` added to ``graph`` (a new one by default); ``FrameError`` when they contradict."""
    graph = graph if graph is not None else FrameGraph()
    for message in messages:
        for edge in message.transforms:
            graph.add(edge.parent_frame, edge.child_frame, matrix_from_transform(edge.transform))
    return graph
