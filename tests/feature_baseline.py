"""OpenCV's per-frame recipe for a known planar image, as its tutorials teach it: the reference that
the natural-feature tracker is compared with.

SIFT keypoints and descriptors (``cv2.SIFT_create``), brute-force L2 matching (``cv2.BFMatcher``:
exact, so the figures do not depend on FLANN's random trees) with k = 2 and Lowe's ratio test at
``RATIO``, ``cv2.findHomography`` with ``cv2.USAC_MAGSAC``; for a pose, ``cv2.solvePnP`` with
``SOLVEPNP_IPPE`` on the homography's inliers, their points on the target plane in metres. No pyramid
of the reference image, no refinement beyond OpenCV's, no state from frame to frame.

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
    """SIFT features of a reference image: ``points`` (N, 2) float32 pixels, ``descriptors`` (N, 128)
    float32, ``size_px`` (width, height)."""

    points: np.ndarray
    descriptors: np.ndarray
    size_px: tuple[int, int]


class SiftBaseline:
    """The tutorial recipe against one reference image (grey, (H, W) uint8), described once."""

    def __init__(self, reference: np.ndarray):
        self.sift = cv2.SIFT_create()
        self.matcher = cv2.BFMatcher(cv2.NORM_L2)
        self.reference = self._describe(reference)

    def _describe(self, grey: np.ndarray) -> Reference:
        keypoints, descriptors = self.sift.detectAndCompute(grey, None)
        points = np.float32([k.pt for k in keypoints]).reshape(-1, 2)
        if descriptors is None:
            descriptors = np.zeros((0, 128), np.float32)
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
