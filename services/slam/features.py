"""The features SLAM works on: ORB keypoints of one frame, undistorted, with their pyramid levels.

Pixels are ideal pinhole pixels of the camera's ``K`` (its distortion undone), x right, y down, the
centre of the top-left pixel at (0, 0). A keypoint found on pyramid level ``l`` is located to about
``scale_factor ** l`` px: that is its ``sigmas`` entry, the standard deviation every reprojection
test and optimisation weighs it by.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.detection.grey import as_grey8
from services.detection.keypoints.detector import KeypointDetector, KeypointParams
from services.geometry.camera import CameraModel, undistort_pixels

__all__ = ["FrameFeatures", "FeatureExtractor"]


@dataclass(frozen=True)
class FrameFeatures:
    """N keypoints of one frame: ``pixels`` (N, 2) float64 undistorted px; ``levels`` (N,) int64
    pyramid levels; ``angles`` (N,) float32 degrees (OpenCV's convention); ``descriptors`` (N, 32)
    uint8 ORB; ``sigmas`` (N,) float64 px, ``scale_factor ** levels``."""

    pixels: np.ndarray
    levels: np.ndarray
    angles: np.ndarray
    descriptors: np.ndarray
    sigmas: np.ndarray

    def __len__(self) -> int:
        return len(self.pixels)


class FeatureExtractor:
    """ORB keypoints spread over a grid (``services.detection.keypoints.detector``), their pixels undistorted
    through ``camera``'s ``K`` and ``dist``."""

    def __init__(self, camera: CameraModel, max_count: int, levels: int, scale_factor: float, fast_threshold: int):
        self.camera = camera
        self.scale_factor = scale_factor
        self.levels = levels
        self._distorted = bool(np.any(np.asarray(camera.dist, dtype=np.float64) != 0))
        self._detector = KeypointDetector(KeypointParams(method="orb", max_count=max_count, spread="grid",
                                                         levels=levels, scale_factor=scale_factor,
                                                         fast_threshold=fast_threshold))

    def extract(self, image: np.ndarray) -> FrameFeatures:
        """The features of a grey or BGR(A) (H, W[, C]) uint8 / uint16 image."""
        keypoints = self._detector.detect(as_grey8(image))
        pixels = keypoints.points.astype(np.float64)
        if self._distorted:
            pixels = undistort_pixels(pixels, self.camera.K, self.camera.dist)
        levels = np.clip(keypoints.octaves.astype(np.int64), 0, self.levels - 1)
        return FrameFeatures(pixels=pixels.reshape(-1, 2), levels=levels, angles=keypoints.angles,
                             descriptors=keypoints.descriptors,
                             sigmas=np.power(self.scale_factor, levels.astype(np.float64)))
