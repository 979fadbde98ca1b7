"""Marker distance and corner bias on a blurred, noisy, unevenly lit sequence, side by side.

The sequence (``SCENE``): the synthetic ``markers`` scene with two markers of 55 mm, the camera
0.3-1.0 m from them (markers 33-110 px wide at 640x480), a gaussian blur of 1 px, noise of 1 grey
level, a light that changes by up to 30 % over time and across the image, each pixel an area sample
(``supersample`` 4), 150 frames 0.2 s apart; once with AprilTag 36h11 markers, once with ArUco
4x4 ones (``FAMILIES``).

Per detected marker that the ground truth lists, each side's error: the mean of its two corners'
detected minus projected true positions, split into the component along the side's outward normal
(positive: the marker measured too large) and along the side (TL -> TR, TR -> BR, ...). Pose errors
as ``tests.accuracy.report.pose_errors``: rotation (deg), translation and signed range (% of the
true distance).

Methods, on the same frames:

* ``artrack``: ``MarkerDetector`` with its defaults (``lines`` corners) and ``MarkerPoseEstimator``
  (``ippe+lm``);
* ``opencv_apriltag``: ``MarkerDetector(refinement="apriltag")`` (OpenCV's CORNER_REFINE_APRILTAG) and
  ``cv2.solvePnP(SOLVEPNP_IPPE_SQUARE)`` per marker;
* ``apriltag3`` (AprilTag 36h11 only, when ``pupil_apriltags`` imports): AprilTag 3's own detector
  (``refine_edges``, full resolution) and its own pose (orthogonal iteration). Its pixels have their
  origin at the top-left pixel's corner, so its corners are moved by -0.5 px and it is given the
  principal point + 0.5 px; its tag frame is OpenCV's turned by 180 deg about y
  (``R_opencv = R_apriltag @ diag(-1, 1, -1)``).

``python -m tests.accuracy.marker_range`` prints one JSON line per family and method (about 2 min:
OpenCV's apriltag refinement takes 0.2-0.3 s a frame); ``python -m tests.accuracy.marker_range apriltag3``
one line of AprilTag 3's exact medians on the AprilTag sequence (exit ``NOT_INSTALLED`` without it). The
tests run AprilTag 3 that way, in a process of its own: its C library corrupts its heap now and then
(pupil-labs/apriltags#39, open), which must not take a test worker down with it.
"""

from __future__ import annotations

import contextlib
import json
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

from services.detection.markers.detector import MarkerDetector
from services.estimation.markers.map import marker_corners
from services.estimation.markers.pose import MarkerPoseEstimator
from services.geometry.camera import project_points
from services.geometry.rotation import matrix_from_rotvec
from services.geometry.se3 import make_transform, transform_points
from services.synthetic import make_scene
from services.synthetic.markers import MarkersScene
from tests.accuracy.report import pose_errors

LENGTH_M = 0.055
SCENE = {"ids": (0, 1), "marker_length": LENGTH_M, "distance": (0.3 / LENGTH_M, 1.0 / LENGTH_M), "blur_px": 1.0,
         "noise_std": 1.0, "lighting": 0.3, "supersample": 4, "fps": 5.0, "seed": 3}
FRAMES = 150
FAMILIES = ("DICT_APRILTAG_36h11", "DICT_4X4_50")
DISTANCE_BINS_M = (0.3, 0.45, 0.65, 0.85, 1.05)
APRILTAG3_TO_OPENCV = np.diag([-1.0, 1.0, -1.0])

Found = list[tuple[int, np.ndarray, np.ndarray]]
"""One frame's markers as a method sees them: ``(id, (4, 2) corners px, (4, 4) T_cam_marker)``."""


@dataclass(frozen=True)
class Scores:
    """A method's results over a sequence, one row per view the truth lists and the method found.

    ``distance_m`` (V,); ``normal_px``, ``along_px`` (V, 4) per side (top, right, bottom, left as printed);
    ``rotation_deg``, ``translation_pct``, ``range_pct`` (V,); ``truth_views`` the views the truth lists;
    ``ms_per_frame`` the method's median time per frame (detection and poses).
    """

    distance_m: np.ndarray
    normal_px: np.ndarray
    along_px: np.ndarray
    rotation_deg: np.ndarray
    translation_pct: np.ndarray
    range_pct: np.ndarray
    truth_views: int
    ms_per_frame: float

    def summary(self) -> dict[str, object]:
        """Medians, per side and per distance bin, as printed."""
        bins = np.digitize(self.distance_m, DISTANCE_BINS_M)
        by_distance = {f"{DISTANCE_BINS_M[b - 1]}-{DISTANCE_BINS_M[b]} m": {
            "views": int(np.sum(bins == b)), "normal_px": round(float(np.median(self.normal_px[bins == b])), 4),
            "range_pct": round(float(np.median(self.range_pct[bins == b])), 4)}
            for b in range(1, len(DISTANCE_BINS_M)) if np.any(bins == b)}
        return {"views": f"{len(self.distance_m)}/{self.truth_views}",
                "rotation_deg": round(float(np.median(self.rotation_deg)), 4),
                "translation_pct": round(float(np.median(self.translation_pct)), 4),
                "range_pct": round(float(np.median(self.range_pct)), 4),
                "normal_px_per_side": np.round(np.median(self.normal_px, axis=0), 4).tolist(),
                "along_px_per_side": np.round(np.median(self.along_px, axis=0), 4).tolist(),
                "by_distance": by_distance, "ms_per_frame": round(self.ms_per_frame, 2)}


def sequence(dictionary: str) -> tuple[MarkersScene, list[tuple[np.ndarray, dict[int, np.ndarray]]]]:
    """The scene of ``dictionary`` and its frames: (H, W) image and marker id -> true ``T_cam_marker``."""
    scene = make_scene("markers", dictionary=dictionary, **SCENE)
    assert isinstance(scene, MarkersScene)
    frames = []
    for index in range(FRAMES):
        frame = scene.render(index)
        frames.append((frame.images["cam0"], {int(child.split("/")[1]): T for _, child, T in frame.truth["cam0"]}))
    return scene, frames


def side_errors(corners: np.ndarray, exact: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per side of a quad, (4,) each: the mean error of its two ``corners`` (4, 2) against ``exact`` (4, 2)
    (clockwise in the image) along its outward normal and along the side."""
    error = corners - exact
    side = np.roll(exact, -1, axis=0) - exact
    along = side / np.linalg.norm(side, axis=1)[:, None]
    outward = np.stack([along[:, 1], -along[:, 0]], axis=1)
    mean = 0.5 * (error + np.roll(error, -1, axis=0))
    return np.sum(mean * outward, axis=1), np.sum(mean * along, axis=1)


def score(frames: list[tuple[np.ndarray, dict[int, np.ndarray]]], K: np.ndarray,
          method: Callable[[np.ndarray], Found]) -> Scores:
    """``method`` (image -> its markers) over ``frames``, scored against their truth."""
    rows, times = [], []
    exact_corners = marker_corners(LENGTH_M)
    for image, truth in frames:
        start = time.perf_counter()
        found = method(image)
        times.append(time.perf_counter() - start)
        for marker_id, corners, T in found:
            if marker_id not in truth:
                continue
            T_true = truth[marker_id]
            normal, along = side_errors(corners, project_points(transform_points(T_true, exact_corners), K))
            rotation, translation, range_error, _ = pose_errors(T, T_true)
            rows.append((np.linalg.norm(T_true[:3, 3]), *normal, *along, rotation, translation, range_error))
    table = np.array(rows)
    return Scores(table[:, 0], table[:, 1:5], table[:, 5:9], table[:, 9], table[:, 10], table[:, 11],
                  sum(len(truth) for _, truth in frames), 1e3 * float(np.median(times)))


def artrack(dictionary: str, K: np.ndarray) -> Callable[[np.ndarray], Found]:
    """The default detector and pose estimator, the estimator keeping its state from frame to frame."""
    detector = MarkerDetector(dictionary, marker_length=LENGTH_M)
    estimator = MarkerPoseEstimator()

    def run(image: np.ndarray) -> Found:
        found = detector.detect(image)
        poses = {pose.target: pose.T for pose in estimator.estimate(found.ids, found.corners, found.side_m, K).poses}
        return [(int(i), c.astype(np.float64), poses[f"marker/{i}"])
                for i, c in zip(found.ids, found.corners, strict=True) if f"marker/{i}" in poses]
    return run


def opencv_apriltag(dictionary: str, K: np.ndarray) -> Callable[[np.ndarray], Found]:
    """OpenCV's AprilTag corner refinement and IPPE_SQUARE per marker."""
    detector = MarkerDetector(dictionary, marker_length=LENGTH_M, refinement="apriltag")
    points = marker_corners(LENGTH_M)

    def run(image: np.ndarray) -> Found:
        found = detector.detect(image)
        result = []
        for marker_id, corners in zip(found.ids, found.corners, strict=True):
            _, rvec, tvec = cv2.solvePnP(points, corners, K, None, flags=cv2.SOLVEPNP_IPPE_SQUARE)
            result.append((int(marker_id), corners.astype(np.float64), make_transform(matrix_from_rotvec(rvec), tvec)))
        return result
    return run


def apriltag3(K: np.ndarray) -> Callable[[np.ndarray], Found]:
    """AprilTag 3 (``pupil_apriltags``, tag36h11) with its own pose; ImportError when it is not installed."""
    from pupil_apriltags import Detector

    detector = Detector(families="tag36h11", nthreads=1, quad_decimate=1.0, refine_edges=True)
    camera = (K[0, 0], K[1, 1], K[0, 2] + 0.5, K[1, 2] + 0.5)

    def run(image: np.ndarray) -> Found:
        result = []
        for tag in detector.detect(image, estimate_tag_pose=True, camera_params=camera, tag_size=LENGTH_M):
            corners = np.asarray(tag.corners, dtype=np.float64)[[1, 0, 3, 2]] - 0.5  # its order: TR, TL, BL, BR
            T = make_transform(np.asarray(tag.pose_R) @ APRILTAG3_TO_OPENCV, np.asarray(tag.pose_t).ravel())
            result.append((int(tag.tag_id), corners, T))
        return result
    return run


NOT_INSTALLED = 5
"""Exit code of ``python -m tests.accuracy.marker_range apriltag3`` when ``pupil_apriltags`` does not import."""


def reference_medians() -> int:
    """Print AprilTag 3's views found, views listed and exact median rotation (deg) and translation (% of
    distance) on the AprilTag 36h11 sequence as one JSON line; the exit code."""
    scene, frames = sequence("DICT_APRILTAG_36h11")
    try:
        method = apriltag3(scene.cameras[0].K)
    except ImportError:
        return NOT_INSTALLED
    theirs = score(frames, scene.cameras[0].K, method)
    print(json.dumps({"views": len(theirs.distance_m), "truth_views": theirs.truth_views,
                      "rotation_deg": float(np.median(theirs.rotation_deg)),
                      "translation_pct": float(np.median(theirs.translation_pct)), "summary": theirs.summary()}))
    return 0


def main() -> None:
    if sys.argv[1:] == ["apriltag3"]:
        sys.exit(reference_medians())
    for dictionary in FAMILIES:
        scene, frames = sequence(dictionary)
        K = scene.cameras[0].K
        methods = {"artrack": artrack(dictionary, K), "opencv_apriltag": opencv_apriltag(dictionary, K)}
        if dictionary == "DICT_APRILTAG_36h11":
            with contextlib.suppress(ImportError):
                methods["apriltag3"] = apriltag3(K)
        for name, method in methods.items():
            print(json.dumps({"family": dictionary, "method": name, **score(frames, K, method).summary()}), flush=True)


if __name__ == "__main__":
    main()
