"""Blobs of one image: bright IR spots by threshold, any spot by the Laplacian of Gaussian, coloured markers by hue.

Every detector returns ``Blobs`` (``bright``): centres (N, 2) in pixels and their shape. ``node`` is the blobs node."""

from __future__ import annotations

from services.detection.blobs.bright import BlobFlag, Blobs, IrBlobParams, ShapeParams, detect_ir_blobs
from services.detection.blobs.colour import ColourBlobParams, HueModel, HueWindow, detect_colour_blobs
from services.detection.blobs.scale_space import LogBlobParams, detect_log_blobs

__all__ = [
    "BlobFlag",
    "Blobs",
    "ColourBlobParams",
    "HueModel",
    "HueWindow",
    "IrBlobParams",
    "LogBlobParams",
    "ShapeParams",
    "detect_colour_blobs",
    "detect_ir_blobs",
    "detect_log_blobs",
]
