"""Marker poses of a folder of images (or any images) in this process: no bus, no nodes.

The marker tracker without its processes, for scripts, notebooks and batch jobs::

    from services.estimation.markers.offline import track_folder

    for frame in track_folder("shots/", "cam0.yaml", dictionary="DICT_4X4_50", marker_length=0.05):
        for target, pose in frame.poses.items():
            print(frame.path.name, target, pose.state, pose.T_camera_target[:3, 3], pose.reprojection_rms_px)

``track_images`` takes any iterable of images instead of a folder. Both run what the marker
pose node runs on each frame (``services.estimation.markers.node`` with ``input = "images"``): the
detector ``marker_tracking.marker_detector`` builds (with the calibration for its corner
refinement), ``MarkerPoseEstimator`` (its ambiguity tracking carries from frame to frame, so give
frames in order) and ``marker_tracking.TargetTracks`` for the ``lost`` poses. Options are the
node's: the detector settings (``dictionary``, ``marker_length``, ``lengths``, ``refinement``,
``parameters``, see ``services.detection.markers.settings``), ``board`` (a marker map YAML, as
``artrack markers print --board`` writes, or a ``MarkerMap``) and the estimator's options
(``method``, ``corner_sigma_px``, ..., see ``pose.MarkerPoseOptions``).

Per frame a ``TrackedFrame``: the detections and, per target (``marker/<id>`` or the board's
name), a ``TargetPose``: state ``tracking`` with ``T_camera_target`` (4, 4), the reprojection
RMS (undistorted px), the corners used, the ambiguity flag and the 6x6 covariance; or state
``lost`` (identity, NaN RMS) once for a target posed in the previous frame and not in this
one. Markers without a pose are counted by reason in ``skipped``. The camera frame is
OpenCV's (x right, y down, z forward); the marker frame ArUco's (x right, y up, z out).
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from services.calibration.camera_info import read_camera_info
from services.calibration.image_folder import IMAGE_SUFFIXES, folder_entries, read_image
from services.detection.markers.detector import MarkerDetector, MarkerFound
from services.detection.markers.settings import DetectorSettings
from services.estimation.markers.map import MarkerMap, load_marker_map
from services.estimation.markers.pose import MarkerPoseEstimator, MarkerPoseOptions
from services.estimation.markers.tracking import TargetTracks, marker_detector
from services.geometry.camera import CameraModel

__all__ = ["TargetPose", "TrackedFrame", "track_folder", "track_images"]


@dataclass(frozen=True)
class TargetPose:
    """One target in one frame. ``T_camera_target``: (4, 4), maps target coordinates (m) into the camera frame;
    ``reprojection_rms_px``: RMS corner residual, undistorted px; ``corners``: corners used; ``covariance``:
    (6, 6) over (tx, ty, tz, rx, ry, rz) in the target frame, None when lost."""

    state: Literal["tracking", "lost"]
    T_camera_target: np.ndarray
    reprojection_rms_px: float = float("nan")
    corners: int = 0
    ambiguous: bool = False
    covariance: np.ndarray | None = None
    marker_ids: tuple[int, ...] = ()


@dataclass(frozen=True)
class TrackedFrame:
    """Frame ``index`` (its ``path`` and folder time ``time_s`` when it came from a folder): ``detections``,
    ``poses`` by target, ``skipped`` markers or boards without a pose by reason
    (``services.estimation.markers.pose.SkipReason``)."""

    index: int
    detections: MarkerFound
    poses: dict[str, TargetPose]
    skipped: dict[str, int] = field(default_factory=dict)
    path: Path | None = None
    time_s: float | None = None


def _camera(camera: CameraModel | str | Path) -> CameraModel:
    return camera if isinstance(camera, CameraModel) else read_camera_info(Path(camera))


def _board(board: MarkerMap | str | Path | None) -> MarkerMap | None:
    return board if board is None or isinstance(board, MarkerMap) else load_marker_map(board)


def track_images(images: Iterable[np.ndarray], camera: CameraModel | str | Path, *,
                 board: MarkerMap | str | Path | None = None, **options: Any) -> Iterator[TrackedFrame]:
    """Track markers in ``images`` (each (H, W) or (H, W, 3|4) uint8 / (H, W) uint16, in order), seen by
    ``camera`` (a CameraModel or a ROS camera_info YAML path). ``options``: fields of ``DetectorSettings``
    and of ``MarkerPoseOptions`` (``method``, ``corner_sigma_px``, ...). Bad options raise ValueError
    before the first image is read."""
    return _track(((n, image, None, None) for n, image in enumerate(images)), camera, board, options)


def track_folder(folder: str | Path, camera: CameraModel | str | Path, **options: Any) -> Iterator[TrackedFrame]:
    """Track markers in the image files of ``folder`` in name order (or the order of its TUM ``rgb.txt``, with its
    times), as ``artrack run marker --source images:FOLDER`` reads them; ``options`` as ``track_images``'.
    A file that cannot be read raises ValueError naming it."""
    folder = Path(folder)
    if not folder.is_dir():
        raise ValueError(f"images:{folder}: no such folder")
    entries = folder_entries(folder)
    if not entries:
        raise ValueError(f"images:{folder}: no image files in {folder} ({', '.join(sorted(IMAGE_SUFFIXES))})")

    def read() -> Iterator[tuple[int, np.ndarray, Path | None, float | None]]:
        for index, (path, time_s) in enumerate(entries):
            image = read_image(path)
            if image is None:
                raise ValueError(f"{path}: cannot read {path}")
            yield index, image, path, time_s

    return _track(read(), camera, options.pop("board", None), options)


def _track(frames: Iterable[tuple[int, np.ndarray, Path | None, float | None]], camera: CameraModel | str | Path,
           board: MarkerMap | str | Path | None, options: dict[str, Any]) -> Iterator[TrackedFrame]:
    """Set everything up now (so bad options fail at the call), then track lazily."""
    model = _camera(camera)
    marker_map = _board(board)
    pose = {name: options[name] for name in MarkerPoseOptions.model_fields if name in options}
    detection = {name: value for name, value in options.items() if name not in pose}
    markers = marker_detector(DetectorSettings.model_validate(detection), marker_map)
    estimator = MarkerPoseEstimator(MarkerPoseOptions.model_validate(pose), marker_map)
    return _frames(frames, model, markers, estimator)


def _frames(frames: Iterable[tuple[int, np.ndarray, Path | None, float | None]], camera: CameraModel,
            markers: MarkerDetector, estimator: MarkerPoseEstimator) -> Iterator[TrackedFrame]:
    tracks = TargetTracks()
    for index, image, path, time_s in frames:
        found = markers.detect(image, camera.K, camera.dist)
        result = estimator.estimate(found.ids, found.corners, found.side_m, camera.K, camera.dist)
        poses = {estimate.target: TargetPose("tracking", estimate.T, estimate.rms_px, estimate.points,
                                             estimate.ambiguous, estimate.covariance, estimate.marker_ids)
                 for estimate in result.poses}
        for target in tracks.update(poses):
            poses[target] = TargetPose("lost", np.eye(4))
        skipped = {reason.value: count for reason, count in result.failures.items()}
        yield TrackedFrame(index, found, poses, skipped, path, time_s)
