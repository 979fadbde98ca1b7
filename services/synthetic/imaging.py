"""Image formation after the geometry: gain (exposure, lighting), gaussian blur and sensor noise.

All functions take and return (H, W) uint8 images and saturate at 0 and 255.
"""

from __future__ import annotations

import cv2
import numpy as np

from services.geometry.trajectory import SinePath

LIGHT_PERIOD_RANGE_S = (6.0, 15.0)


def finish(image: np.ndarray, exposure: float, blur_px: float, noise_std: float, noise_seed: int) -> np.ndarray:
    """Apply the gain ``exposure``, a gaussian blur of sigma ``blur_px`` and noise of ``noise_std`` grey levels.

    The noise is drawn from OpenCV's RNG of the calling thread, reseeded with ``noise_seed``
    first, so the same seed gives the same noise (cv2.randn is several times faster than numpy).
    """
    if exposure != 1.0:
        image = cv2.convertScaleAbs(image, alpha=exposure)
    image = gaussian_blur(image, blur_px)
    if noise_std > 0.0:
        noise = np.empty(image.shape, np.int16)
        cv2.setRNGSeed(noise_seed)
        cv2.randn(noise, 0.0, noise_std)  # type: ignore[call-overload]  # mean and stddev may be numbers
        image = cv2.add(image, noise, dtype=cv2.CV_8U)
    return image


def gaussian_blur(image: np.ndarray, sigma_px: float) -> np.ndarray:
    """``image`` blurred with a gaussian of ``sigma_px`` pixels (unchanged below 0.05 px)."""
    return cv2.GaussianBlur(image, (0, 0), sigma_px) if sigma_px >= 0.05 else image


def apply_gain(image: np.ndarray, gain: np.ndarray) -> np.ndarray:
    """``image * gain`` with ``gain`` a float32 array broadcastable to the image, e.g. (H, 1) + (1, W) terms."""
    return cv2.multiply(image, np.broadcast_to(gain, image.shape).astype(np.float32), dtype=cv2.CV_8U)


class Lighting:
    """Light that changes slowly over time: a global gain around 1 and a gain gradient across the image.

    The gain, and the gain differences between the left and right and between the top and bottom
    image borders, each stay within ``amplitude`` of 1, 0 and 0 (sums of sines of 6-15 s periods
    drawn from ``rng``). ``amplitude`` 0: constant light, images unchanged.
    """

    def __init__(self, rng: np.random.Generator, amplitude: float):
        self.amplitude = amplitude
        self.path = SinePath.random(rng, (1.0, 0.0, 0.0), (amplitude, amplitude, amplitude), LIGHT_PERIOD_RANGE_S)
        """(gain, horizontal slope, vertical slope) over time."""

    def apply(self, image: np.ndarray, time_s: float) -> np.ndarray:
        """(H, W) uint8 ``image`` lit as at ``time_s``."""
        if self.amplitude == 0.0:
            return image
        gain, slope_u, slope_v = self.path(time_s)
        u = np.linspace(-0.5, 0.5, image.shape[1], dtype=np.float32)[None, :]
        v = np.linspace(-0.5, 0.5, image.shape[0], dtype=np.float32)[:, None]
        return apply_gain(image, gain + slope_u * u + slope_v * v)
