"""OpenCV's per-frame recipe for a known planar image, as its tutorials teach it: the references that
the natural-feature tracker is compared with, with either of two features.

* ``SiftBaseline``: SIFT keypoints and descriptors (``cv2.SIFT_create``), brute-force L2 matching;
* ``OrbBaseline``: ORB keypoints and descriptors at OpenCV's defaults (``cv2.ORB_create``: 500
  keypoints, 8 levels), brute-force Hamming matching: the fastest of OpenCV's stock recipes.

Either way: brute-force matching (``cv2.BFMatcher``: exact, so the figures do not depend on FLANN's
random trees) with k = 2 and Lowe's ratio test at ``RATIO``, ``cv2.findHomography`` with
``cv2.USAC_MAGSAC``; for a pose, ``cv2.solvePnP`` with ``SOLVEPNP_IPPE`` on the homography's inliers,
their points on the target plane in metres. No pyramid of the reference image beyond the detector's
own, no refinement beyond OpenCV's, no state from frame to frame.

Pixels: the centre of the top-left pixel at (0, 0). Target frame: origin at the image's centre, x
right, y up, z towards the viewer (``services.estimation.targets.target``). Poses ``T_camera_target`` (4, 4),
OpenCV's camera frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from services.estimation.targets.target import target_points

RATIO = 0.75
THRESHOLD_PX = 3.0
"""The homography's inlier threshold, the same as recognition's."""
MIN_MATCHES = 4


@dataclass(frozen=True)
class Reference:
    """Features of a reference image: ``points`` (N, 2) float32 pixels, ``descriptors`` (N, D) as the
    detector gives them (SIFT: 128 float32; ORB: 32 uint8), ``size_px`` (width, height)."""

    points: np.ndarray
    descriptors: np.ndarray
    size_px: tuple[int, int]


class Baseline:
    """The tutorial recipe against one reference image (grey, (H, W) uint8), described once by
    ``detector`` (an OpenCV ``Feature2D``) and matched by brute force under ``norm``."""

    def __init__(self, reference: np.ndarray, detector: cv2.Feature2D, norm: int):
        self.detector = detector
        self.matcher = cv2.BFMatcher(norm)
        self.reference = self._describe(reference)

    def _describe(self, grey: np.ndarray) -> Reference:
        keypoints, descriptors = self.detector.detectAndCompute(grey, None)
        points = np.float32([k.pt for k in keypoints]).reshape(-1, 2)
        if descriptors is None:
            dtype = np.uint8 if self.detector.descriptorType() == cv2.CV_8U else np.float32
            descriptors = np.zeros((0, self.detector.descriptorSize()), dtype)
        return Reference(points, descriptors, (grey.shape[1], grey.shape[0]))

    def homography(self, grey: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """``(H, reference_pixels, frame_pixels)``: the (3, 3) homography reference pixel -> pixel of the
        (H, W) uint8 ``grey`` image and the (M, 2) pixels of its M inliers in both images; None when
        fewer than four matches pass the ratio test or USAC finds no homography."""
        frame = self._describe(grey)
        if len(frame.descriptors) < 2 or len(self.reference.descriptors) < 2:
            return None
        pairs = self.matcher.knnMatch(self.reference.descriptors, frame.descriptors, k=2)
        good = [m for m, n in (p for p in pairs if len(p) == 2) if m.distance < RATIO * n.distance]
        if len(good) < MIN_MATCHES:
            return None
        source = self.reference.points[[m.queryIdx for m in good]]
        destination = frame.points[[m.trainIdx for m in good]]
        H, mask = cv2.findHomography(source, destination, cv2.USAC_MAGSAC, THRESHOLD_PX)
        if H is None:
            return None
        inliers = mask.ravel().astype(bool)
        return H, source[inliers], destination[inliers]

    def pose(self, grey: np.ndarray, width_m: float, K: np.ndarray) -> np.ndarray | None:
        """(4, 4) ``T_camera_target`` of the reference printed ``width_m`` wide, seen in ``grey`` by the
        distortion-free pinhole ``K`` (3, 3); None when there is no homography or no pose."""
        found = self.homography(grey)
        if found is None:
            return None
        _, reference_pixels, frame_pixels = found
        points = target_points(reference_pixels, self.reference.size_px, width_m)
        solved, rvec, tvec = cv2.solvePnP(points, frame_pixels.astype(np.float64), K, None,
                                          flags=cv2.SOLVEPNP_IPPE)
        if not solved:
            return None
        T = np.eye(4)
        T[:3, :3] = cv2.Rodrigues(rvec)[0]
        T[:3, 3] = tvec.ravel()
        return T


class SiftBaseline(Baseline):
    """The recipe with SIFT (``cv2.SIFT_create()``) and L2 matching."""

    def __init__(self, reference: np.ndarray):
        super().__init__(reference, cv2.SIFT_create(), cv2.NORM_L2)


class OrbBaseline(Baseline):
    """The recipe with ORB at OpenCV's defaults (``cv2.ORB_create()``) and Hamming matching."""

    def __init__(self, reference: np.ndarray):
        super().__init__(reference, cv2.ORB_create(), cv2.NORM_HAMMING)
