"""Marker pose accuracy against the ground truth of the synthetic ``markers`` scene, side by side.

Two data sets of marker views (640x480, markers whose projection spans 5-30 % of the image
width, frames taken in order along the camera path so the estimator's ambiguity tracking works
as it would live):

* ``projected``: the true corners projected exactly, plus Gaussian noise of ``NOISE_PX`` per axis.
* ``rendered``: rendered frames, corners from cv2.aruco.ArucoDetector with CORNER_REFINE_SUBPIX
  (``MarkerDetector(refinement="subpix")``).

Estimators, all on the same corners: ``homography`` (raw normalised-DLT homography pose),
``opencv`` (cv2.solvePnP with SOLVEPNP_IPPE_SQUARE per marker: what OpenCV alone gives),
and ``MarkerPoseEstimator`` with each method (``lm``, ``ippe``, ``ippe+lm``; ``ours`` is the
default method). Figures: median and 90th percentile of the rotation error (deg) and of the
translation error (% of the true distance), the median signed range error (% of the distance,
positive = too far), and the share of views flagged ambiguous. Board lines score the whole
board's pose from all its visible markers (``opencv``: cv2.solvePnP on all their corners).

Corner refinements (``corner_refinement`` lines): the rendered frames again, corners from
``MarkerDetector`` with each refinement (``lines``, the default, and OpenCV's ``none``,
``subpix``, ``contour``, ``apriltag``): per-corner error against the true projected corners
(median, p90, px), the mean offset along the sides' inward normals (px, positive = inside), and
the median rotation (deg), translation (mm and % of distance) and signed range (%) errors of
``MarkerPoseEstimator``'s default method, per marker and for the board. ``photo_board_pose``
lines: the same refinements on OpenCV's ChArUco tutorial photos (``charuco_photos``), when the
data set is there.

``python -m tests.accuracy.report`` prints one JSON line per data set, target kind (``marker``,
``board``) and estimator, then per refinement (about 20 s).
"""

from __future__ import annotations

import json
from dataclasses import dataclass

import cv2
import numpy as np

from services.detection.markers.detector import REFINEMENTS, MarkerDetector
from services.estimation.markers.map import map_from_poses, marker_corners
from services.estimation.markers.pose import DEFAULT_METHOD, METHODS, MarkerPoseEstimator, MarkerPoseOptions, TargetPose
from services.geometry.camera import project_points
from services.geometry.homography import homography_dlt, pose_from_homography
from services.geometry.rotation import matrix_from_rotvec, rotation_angle
from services.geometry.se3 import invert, make_transform, transform_points
from services.synthetic import make_scene
from services.synthetic.markers import MarkersScene
from tests.accuracy.charuco_photos import CHARUCO_PHOTOS, DATA_SET, OCCLUDED_PHOTO, photo_poses
from tests.data import data_root

NOISE_PX = 0.5
WIDTH_RANGE = (0.05, 0.30)
PROJECTED_FRAMES = range(0, 900, 6)
RENDERED_FRAMES = range(0, 900, 15)
SEED = 7


@dataclass(frozen=True)
class View:
    """One marker in one frame: its id, true ``T_cam_marker`` (4, 4) and (4, 2) observed corners (pixels)."""

    marker_id: int
    T_cam_marker: np.ndarray
    corners: np.ndarray


@dataclass(frozen=True)
class Frame:
    """One frame's views and the true ``T_cam_board`` (4, 4)."""

    index: int
    T_cam_board: np.ndarray
    views: list[View]


def true_views(scene: MarkersScene, index: int) -> list[tuple[int, np.ndarray, np.ndarray]]:
    """``(id, T_cam_marker, exact corners (4, 2))`` of the markers of frame ``index`` fully in view and
    spanning ``WIDTH_RANGE`` of the image width."""
    camera = scene.cameras[0]
    T_cam_board = invert(scene.camera_pose(index))
    views = []
    for marker_id, T_board_marker in scene.marker_poses.items():
        T = T_cam_board @ T_board_marker
        points = transform_points(T, marker_corners(scene.marker_length))
        if np.any(points[:, 2] <= 0):
            continue
        pixels = project_points(points, camera.K)
        inside = np.all((pixels >= 0) & (pixels <= (camera.width - 1, camera.height - 1)))
        span = np.ptp(pixels[:, 0]) / camera.width
        if inside and WIDTH_RANGE[0] <= span <= WIDTH_RANGE[1]:
            views.append((marker_id, T, pixels))
    return views


def projected_views(scene: MarkersScene, frames: range = PROJECTED_FRAMES, noise_px: float = NOISE_PX,
                    seed: int = SEED) -> list[Frame]:
    """The frames, their views with exact corners plus Gaussian noise of ``noise_px`` per axis."""
    rng = np.random.default_rng(seed)
    return [Frame(n, invert(scene.camera_pose(n)), [View(i, T, pixels + rng.normal(0.0, noise_px, pixels.shape))
                                                    for i, T, pixels in true_views(scene, n)])
            for n in frames]


def rendered_images(scene: MarkersScene, frames: range = RENDERED_FRAMES) -> dict[int, np.ndarray]:
    """Frame index -> its rendered (H, W) uint8 image."""
    return {n: scene.render(n).images["cam0"] for n in frames}


def detected_views(scene: MarkersScene, frames: range = RENDERED_FRAMES, refinement: str = "subpix",
                   images: dict[int, np.ndarray] | None = None) -> list[Frame]:
    """The rendered frames (``images``, else rendered here), their views with the corners MarkerDetector
    finds with ``refinement`` (``subpix``: ArucoDetector with CORNER_REFINE_SUBPIX, OpenCV alone)."""
    detector = MarkerDetector(scene.dictionary, refinement=refinement)
    images = images if images is not None else rendered_images(scene, frames)
    result = []
    for n in frames:
        detected = detector.detect(images[n])
        found = dict(zip(detected.ids.tolist(), detected.corners, strict=True))
        views = [View(i, T, found[i].astype(np.float64)) for i, T, _ in true_views(scene, n) if i in found]
        result.append(Frame(n, invert(scene.camera_pose(n)), views))
    return result


def corner_errors(frames: list[Frame], length: float, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per corner of every view: its error length (px) and its offset along the inward normals of its
    two sides (px, the mean over both; positive = inside the true quad). Both (4 V,)."""
    lengths, inward = [], []
    for view in (view for frame in frames for view in frame.views):
        exact = project_points(transform_points(view.T_cam_marker, marker_corners(length)), K)
        error = view.corners - exact
        lengths.append(np.linalg.norm(error, axis=1))
        side = np.roll(exact, -1, axis=0) - exact
        normal = np.stack([-side[:, 1], side[:, 0]], axis=1) / np.linalg.norm(side, axis=1)[:, None]
        normal *= np.sign(np.sum(normal * (exact.mean(axis=0) - exact), axis=1))[:, None]
        inward.append(0.5 * (np.sum(error * normal, axis=1) + np.sum(error * np.roll(normal, 1, axis=0), axis=1)))
    return np.concatenate(lengths), np.concatenate(inward)


def pose_errors(T: np.ndarray, T_true: np.ndarray) -> tuple[float, float, float, float]:
    """Rotation error (deg), translation error and signed range error (both % of the true distance)
    and translation error (mm) of ``T`` against ``T_true``."""
    distance = np.linalg.norm(T_true[:3, 3])
    miss = np.linalg.norm(T[:3, 3] - T_true[:3, 3])
    return (float(np.degrees(rotation_angle(T[:3, :3], T_true[:3, :3]))), float(100 * miss / distance),
            float(100 * (np.linalg.norm(T[:3, 3]) - distance) / distance), float(1e3 * miss))


def baseline_poses(views: list[View], K: np.ndarray, length: float) -> dict[str, list[np.ndarray]]:
    """Per view, the raw homography pose and OpenCV's solvePnP IPPE_SQUARE pose (4, 4)."""
    corners = marker_corners(length)
    poses: dict[str, list[np.ndarray]] = {"homography": [], "opencv": []}
    for view in views:
        poses["homography"].append(pose_from_homography(homography_dlt(corners[:, :2], view.corners), K))
        _, rvec, tvec = cv2.solvePnP(corners, view.corners, K, None, flags=cv2.SOLVEPNP_IPPE_SQUARE)
        poses["opencv"].append(make_transform(matrix_from_rotvec(rvec), tvec))
    return poses


def evaluate(frames: list[Frame], K: np.ndarray, length: float) -> dict[str, dict[str, np.ndarray]]:
    """Estimator -> ``{"rotation_deg", "translation_pct", "range_pct": (V,), "ambiguous": (V,) bool}`` over
    all V single-marker views (NaN where an estimator gave no pose). Each method's estimator sees
    the frames in order."""
    views = [view for frame in frames for view in frame.views]
    poses = baseline_poses(views, K, length)
    flags = {name: [False] * len(views) for name in poses}
    for method in METHODS:
        estimator = MarkerPoseEstimator(MarkerPoseOptions(method=method))
        poses[method], flags[method] = [], []
        for frame in frames:
            found = estimate(estimator, frame, K, length)
            for view in frame.views:
                pose = found.get(f"marker/{view.marker_id}")
                poses[method].append(np.full((4, 4), np.nan) if pose is None else pose.T)
                flags[method].append(pose is not None and pose.ambiguous)
    poses["ours"], flags["ours"] = poses[DEFAULT_METHOD], flags[DEFAULT_METHOD]
    return scores(poses, flags, [view.T_cam_marker for view in views])


def evaluate_board(frames: list[Frame], scene: MarkersScene) -> dict[str, dict[str, np.ndarray]]:
    """As ``evaluate`` for the whole board's pose ``T_cam_board`` from all its visible markers at once:
    ``opencv`` is cv2.solvePnP (default SOLVEPNP_ITERATIVE) on all the corners; the methods use the
    scene's board as a marker map."""
    K, length = scene.cameras[0].K, scene.marker_length
    frames = [frame for frame in frames if frame.views]
    board = map_from_poses("board", scene.marker_poses, length)
    poses: dict[str, list[np.ndarray]] = {"opencv": []}
    for frame in frames:
        points = np.concatenate([board.markers[view.marker_id].corners() for view in frame.views])
        pixels = np.concatenate([view.corners for view in frame.views])
        _, rvec, tvec = cv2.solvePnP(points, pixels, K, None)
        poses["opencv"].append(make_transform(matrix_from_rotvec(rvec), tvec))
    flags = {"opencv": [False] * len(frames)}
    for method in METHODS:
        estimator = MarkerPoseEstimator(MarkerPoseOptions(method=method), marker_map=board)
        found = [estimate(estimator, frame, K, length).get("board") for frame in frames]
        poses[method] = [np.full((4, 4), np.nan) if pose is None else pose.T for pose in found]
        flags[method] = [pose is not None and pose.ambiguous for pose in found]
    poses["ours"], flags["ours"] = poses[DEFAULT_METHOD], flags[DEFAULT_METHOD]
    return scores(poses, flags, [frame.T_cam_board for frame in frames])


def estimate(estimator: MarkerPoseEstimator, frame: Frame, K: np.ndarray, length: float) -> dict[str, TargetPose]:
    """Target name -> pose the estimator gives for the frame's views."""
    if not frame.views:
        return {}
    corners = np.array([view.corners for view in frame.views])
    result = estimator.estimate([view.marker_id for view in frame.views], corners, length, K)
    return {pose.target: pose for pose in result.poses}


def scores(poses: dict[str, list[np.ndarray]], flags: dict[str, list[bool]],
           truth: list[np.ndarray]) -> dict[str, dict[str, np.ndarray]]:
    """Per estimator, the rotation (deg), translation and signed range (%), translation (mm) errors of
    its poses and its ambiguity flags."""
    result = {}
    for name, estimates in poses.items():
        pairs = np.array([pose_errors(T, T_true) for T, T_true in zip(estimates, truth, strict=True)])
        result[name] = {"rotation_deg": pairs[:, 0], "translation_pct": pairs[:, 1], "range_pct": pairs[:, 2],
                        "translation_mm": pairs[:, 3], "ambiguous": np.array(flags[name], dtype=bool)}
    return result


def summary(errors: dict[str, np.ndarray]) -> dict[str, float | int]:
    """Median and p90 of one estimator's errors, the median signed range error (a scale bias shows
    here), its view count, missing poses and ambiguous share."""
    rotation, translation = errors["rotation_deg"], errors["translation_pct"]
    found = np.isfinite(rotation)
    return {"views": int(len(rotation)), "missing": int(np.sum(~found)),
            "median_rotation_deg": round(float(np.median(rotation[found])), 4),
            "p90_rotation_deg": round(float(np.percentile(rotation[found], 90)), 4),
            "median_translation_pct": round(float(np.median(translation[found])), 4),
            "p90_translation_pct": round(float(np.percentile(translation[found], 90)), 4),
            "median_range_error_pct": round(float(np.median(errors["range_pct"][found])), 4),
            "ambiguous_share": round(float(np.mean(errors["ambiguous"])), 4)}


def refinement_lines(scene: MarkersScene, images: dict[int, np.ndarray]) -> list[dict]:
    """Per corner refinement, on the rendered frames: corner errors against the true corners and the
    poses ``MarkerPoseEstimator`` (default method) gives from them, single markers and board."""
    K, length = scene.cameras[0].K, scene.marker_length
    lines = []
    for refinement in REFINEMENTS:
        frames = detected_views(scene, refinement=refinement, images=images)
        error, inward = corner_errors(frames, length, K)
        line = {"bench": "corner_refinement", "refinement": refinement, "corners": int(len(error)),
                "median_corner_px": round(float(np.median(error)), 4),
                "p90_corner_px": round(float(np.percentile(error, 90)), 4),
                "mean_inward_px": round(float(np.mean(inward)), 4)}
        for target, results in (("marker", evaluate(frames, K, length)), ("board", evaluate_board(frames, scene))):
            errors = results["ours"]
            line |= {f"{target}_median_rotation_deg": round(float(np.median(errors["rotation_deg"])), 4),
                     f"{target}_median_translation_mm": round(float(np.median(errors["translation_mm"])), 3),
                     f"{target}_median_translation_pct": round(float(np.median(errors["translation_pct"])), 4),
                     f"{target}_median_range_error_pct": round(float(np.median(errors["range_pct"])), 4)}
        lines.append(line)
    return lines


def photo_lines() -> list[dict]:
    """Per ChArUco tutorial photo and refinement, the board pose figures of ``charuco_photos.photo_poses``
    (none when the data set is absent)."""
    folder = data_root() / DATA_SET
    if not folder.is_dir():
        return []
    return [{"bench": "photo_board_pose", "photo": name, "refinement": refinement,
             **{key: round(value, 4) if isinstance(value, float) else value
                for key, value in photo_poses(folder, name, refinement).items()}}
            for name in (*CHARUCO_PHOTOS, OCCLUDED_PHOTO) for refinement in REFINEMENTS]


def report_lines() -> list[dict]:
    """One JSON-able line per data set, target kind and estimator; then per corner refinement on the
    rendered frames and on the ChArUco photos."""
    scene = make_scene("markers")
    K, length = scene.cameras[0].K, scene.marker_length
    images = rendered_images(scene)
    lines = []
    for data, frames in (("projected", projected_views(scene)), ("rendered", detected_views(scene, images=images))):
        for target, results in (("marker", evaluate(frames, K, length)), ("board", evaluate_board(frames, scene))):
            for name, errors in results.items():
                lines.append({"bench": "marker_accuracy", "data": data, "target": target, "estimator": name,
                              "noise_px": NOISE_PX if data == "projected" else None, **summary(errors)})
    return lines + refinement_lines(scene, images) + photo_lines()


if __name__ == "__main__":
    for line in report_lines():
        print(json.dumps(line), flush=True)
