"""The marker tracker: planar-marker and marker-map poses of one camera, frame after frame.

``pose`` holds the estimator (``T_camera_marker`` (4, 4) and ``T_camera_<map>``), ``ambiguity`` the choice
between a planar target's two candidate poses, ``map`` the marker maps (markers placed in one frame),
``tracking`` what a tracker keeps between frames, ``offline`` the tracker run in-process over images, and
``node`` the marker pose node."""

from __future__ import annotations

from services.estimation.markers.ambiguity import AmbiguityTracker
from services.estimation.markers.map import (
    MapMarker,
    MarkerMap,
    MarkerMapError,
    grid_map,
    load_marker_map,
    parse_marker_map,
    save_marker_map,
)
from services.estimation.markers.offline import TrackedFrame, track_folder, track_images
from services.estimation.markers.pose import (
    FrameEstimate,
    MarkerPoseEstimator,
    MarkerPoseOptions,
    SkipReason,
    TargetPose,
)
from services.estimation.markers.tracking import TargetTracks, marker_detector

__all__ = [
    "AmbiguityTracker",
    "FrameEstimate",
    "MapMarker",
    "MarkerMap",
    "MarkerMapError",
    "MarkerPoseEstimator",
    "MarkerPoseOptions",
    "SkipReason",
    "TargetPose",
    "TargetTracks",
    "TrackedFrame",
    "grid_map",
    "load_marker_map",
    "marker_detector",
    "parse_marker_map",
    "save_marker_map",
    "track_folder",
    "track_images",
]
