"""What travels between artrack processes: messages, key expressions, the wire codec.

This package depends on pydantic and numpy only, so any client can use it alone.
Importing it registers every message type with the codec.
"""

from protocol.codec import DecodeError, Peeked, decode, encode, peek, to_json
from protocol.detections import Blobs, Keypoints, MarkerDetections
from protocol.flow import FlowAck, FlowEnd
from protocol.keys import Keys
from protocol.maps import Keyframes, PointCloud, Trajectory
from protocol.message import Header, Message, message_type, message_types
from protocol.mocap import Points3D
from protocol.poses import GroundTruth, Pose, PoseQuality, RigidBodies, RigidBody
from protocol.sensors import CameraInfo, Image, RegionOfInterest
from protocol.spatial import RIG_FRAME, FrameTransform, StaticTransforms, Transform
from protocol.system import (
    ClientState,
    ConfigAnswer,
    ConfigChange,
    ErrorReport,
    NodeStats,
    PipelineHealth,
    ReplayCommand,
    ReplayControl,
    ReplayStatus,
    StageTimings,
    StreamStats,
    Subscription,
    SupervisedNode,
    SyncInputStats,
    SyncStats,
)
from protocol.targets import ImageTarget, ImageTargets
from protocol.tracking_state import TrackingState

__all__ = [
    "Blobs", "CameraInfo", "ClientState", "ConfigAnswer", "ConfigChange", "DecodeError",
    "ErrorReport", "FlowAck", "FlowEnd", "FrameTransform", "GroundTruth", "Header", "Image", "ImageTarget",
    "ImageTargets", "Keyframes", "Keypoints", "Keys", "MarkerDetections",
    "Message", "NodeStats", "Peeked", "PipelineHealth", "PointCloud", "Points3D", "Pose", "PoseQuality", "RIG_FRAME",
    "RegionOfInterest", "ReplayCommand", "ReplayControl", "ReplayStatus", "RigidBodies", "RigidBody",
    "StageTimings", "StaticTransforms", "StreamStats", "Subscription", "SupervisedNode", "SyncInputStats", "SyncStats",
    "TrackingState", "Trajectory", "Transform", "decode", "encode", "message_type", "message_types", "peek", "to_json"
]
