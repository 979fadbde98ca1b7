"""Corner responses written out: the structure tensor of Sobel gradients, Harris's and Shi-Tomasi's measures.

For a grey image ``I`` with Sobel gradients ``Ix``, ``Iy`` (aperture ``ksize``), the structure
tensor at a pixel sums the gradients' products over a window ``w`` of ``block_size`` px around it::

    M = sum_w [[Ix Ix, Ix Iy],
               [Ix Iy, Iy Iy]]  =  [[a, b], [b, c]]

    harris     = det M - k trace(M)^2 = a c - b^2 - k (a + c)^2
    shi_tomasi = the smaller eigenvalue = (a + c) / 2 - sqrt(((a - c) / 2)^2 + b^2)

Both are large where the image changes in every direction (a corner), the Harris response is
negative along an edge and near zero in flat parts.

The gradients are scaled as OpenCV scales them, by ``1 / (2^(ksize - 1) * block_size)`` and a
further ``1 / 255`` for uint8 images, so with the ``box`` window (an unweighted sum, the
window of ``cv2.cornerHarris`` and ``cv2.cornerMinEigenVal``) the figures are theirs. The
``gaussian`` window weighs the products by a Gaussian of standard deviation ``block_size / 2``,
its weights summing to ``block_size^2`` like the box's, so responses keep their magnitude.
Beyond the image the pixels are mirrored (``border``, OpenCV's default ``BORDER_REFLECT_101``).
An even ``block_size`` puts the window's centre half a pixel up and left of the pixel, as OpenCV does.
"""

from __future__ import annotations

from typing import Literal

import cv2
import numpy as np

__all__ = ["Window", "harris_response", "min_eigenvalue", "structure_tensor"]

Window = Literal["box", "gaussian"]


def structure_tensor(image: np.ndarray, block_size: int = 3, ksize: int = 3, window: Window = "box",
                     border: int = cv2.BORDER_REFLECT_101) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The structure tensor's entries ``(a, b, c)``, each (H, W) float32, of an (H, W) uint8 or float32 image."""
    if image.ndim != 2 or image.dtype not in (np.uint8, np.float32):
        raise ValueError(f"image must be (H, W) uint8 or float32, not {image.shape} {image.dtype}")
    if block_size < 1 or ksize not in (1, 3, 5, 7):
        raise ValueError(f"block_size must be >= 1 and ksize 1, 3, 5 or 7, not {block_size} and {ksize}")
    scale = 1.0 / (2 ** (ksize - 1) * block_size * (255.0 if image.dtype == np.uint8 else 1.0))
    gx = cv2.Sobel(image, cv2.CV_32F, 1, 0, ksize=ksize, scale=scale, borderType=border)
    gy = cv2.Sobel(image, cv2.CV_32F, 0, 1, ksize=ksize, scale=scale, borderType=border)
    return (_window_sum(gx * gx, block_size, window, border), _window_sum(gx * gy, block_size, window, border),
            _window_sum(gy * gy, block_size, window, border))


def harris_response(image: np.ndarray, block_size: int = 3, ksize: int = 3, k: float = 0.04,
                    window: Window = "box", border: int = cv2.BORDER_REFLECT_101) -> np.ndarray:
    """(H, W) float32: ``det M - k trace(M)^2`` of the structure tensor ``M`` at every pixel."""
    a, b, c = structure_tensor(image, block_size, ksize, window, border)
    trace = a + c
    return a * c - b * b - np.float32(k) * trace * trace


def min_eigenvalue(image: np.ndarray, block_size: int = 3, ksize: int = 3, window: Window = "box",
                   border: int = cv2.BORDER_REFLECT_101) -> np.ndarray:
    """(H, W) float32: the smaller eigenvalue of the structure tensor at every pixel (Shi and Tomasi's measure)."""
    a, b, c = structure_tensor(image, block_size, ksize, window, border)
    half_difference = (a - c) * np.float32(0.5)
    return (a + c) * np.float32(0.5) - np.sqrt(half_difference * half_difference + b * b)


def _window_sum(values: np.ndarray, block_size: int, window: Window, border: int) -> np.ndarray:
    if window == "box":
        return cv2.boxFilter(values, -1, (block_size, block_size), normalize=False, borderType=border)
    blurred = cv2.GaussianBlur(values, (0, 0), block_size / 2.0, borderType=border)
    return blurred * np.float32(block_size * block_size)
