"""The natural-feature tracker: printed images found and followed in one camera's frames.

``target`` holds a target as data (its image, size and features on the target plane), ``features`` the
keypoints it is described by, ``library`` the folder of targets, ``check`` how trackable an image is,
``recognition`` finds a target from scratch, ``tracking`` follows it from frame to frame (``measure``,
``alignment`` and ``pose`` refine and solve ``T_camera_target`` (4, 4)), and ``node`` is the features node."""

from __future__ import annotations

from services.estimation.targets.alignment import AlignmentOptions, TargetAligner
from services.estimation.targets.check import Trackability, check_image
from services.estimation.targets.library import TargetInfo, TargetLibrary, TargetLibraryError, default_library_dir
from services.estimation.targets.measure import MeasureOptions
from services.estimation.targets.pose import PlanarFit, fit_planar_pose
from services.estimation.targets.recognition import Recognition, RecognitionOptions, TargetRecognizer
from services.estimation.targets.target import Target, build_target
from services.estimation.targets.tracking import TargetPose, TargetTracker, TrackingOptions, track_targets

__all__ = [
    "AlignmentOptions",
    "MeasureOptions",
    "PlanarFit",
    "Recognition",
    "RecognitionOptions",
    "Target",
    "TargetAligner",
    "TargetInfo",
    "TargetLibrary",
    "TargetLibraryError",
    "TargetPose",
    "TargetRecognizer",
    "TargetTracker",
    "Trackability",
    "TrackingOptions",
    "build_target",
    "check_image",
    "default_library_dir",
    "fit_planar_pose",
    "track_targets",
]
