"""Blobs node: the bright spots (IR spheres, LEDs) or coloured markers of one camera's frames.

Each frame on ``<camera>/image`` yields one ``protocol.detections.Blobs`` on ``<camera>/blobs`` with
the frame's header unchanged, zero rows when nothing was found. ``method`` picks the detector:

* ``ir`` (default, ``services.detection.blobs.bright``): threshold, connected components, weighted
  centroid. Takes mono8 and mono16 frames (``threshold`` is on the 8-bit scale: a mono16 frame
  is compared with ``threshold * 257``); a bgr8/bgra8 frame is turned grey first.
* ``log`` (``services.detection.blobs.scale_space``): scale-normalised Laplacian of Gaussian, any
  mono8, mono16 or bgr8 frame (bgra8 loses its alpha first).
* ``colour`` (``services.detection.blobs.colour``): pixels whose hue is near ``hue_deg``; needs
  bgr8 (or bgra8) frames. A mono frame gets an empty Blobs and is reported as skipped.

A frame the method cannot work on is counted as skipped and reported
(``services.runtime.frame_detection``). One frame may wait while another is searched (``depth``).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from protocol.detections import BlobMethod, Blobs
from protocol.keys import KeyName
from protocol.message import Header
from services.bus.pubsub import Role
from services.detection.blobs.bright import Blobs as FoundBlobs
from services.detection.blobs.bright import IrBlobParams, detect_ir_blobs
from services.detection.blobs.colour import ColourBlobParams, HueModel, detect_colour_blobs
from services.detection.blobs.scale_space import LogBlobParams, detect_log_blobs
from services.detection.grey import MONO16_SCALE, as_grey
from services.runtime.frame_detection import UnusableFrame, detect_frames
from services.runtime.kind import NodeKind
from services.runtime.node import Node, NodeError


class Params(BaseModel):
    """Which camera, which detector and its main settings."""

    model_config = ConfigDict(extra="forbid")

    camera: KeyName = "cam0"
    method: BlobMethod = Field(default="ir", description="ir (threshold), log (scale space) or colour (hue)")
    threshold: float = Field(default=60.0, ge=0, le=255, description="ir: grey level (8-bit scale) blobs exceed")
    min_area: float = Field(default=3.0, ge=0, description="smallest blob kept, px^2")
    max_area: float = Field(default=10000.0, gt=0, description="largest blob kept, px^2")
    min_sigma: float = Field(default=1.0, ge=0.3, description="log: smallest scale, px")
    max_sigma: float = Field(default=10.0, ge=0.3, description="log: largest scale, px")
    log_threshold: float = Field(default=0.05, gt=0, le=1, description="log: least response (contrast, 0 to 1)")
    hue_deg: float = Field(default=0.0, ge=0, lt=360, description="colour: the markers' hue, degrees")
    hue_width_deg: float = Field(default=8.0, gt=0, le=180, description="colour: half-width of the hue window, deg")
    min_saturation: float = Field(default=80.0, ge=0, le=255, description="colour: least saturation, 0..255")
    min_value: float = Field(default=60.0, ge=0, le=255, description="colour: least value, 0..255")
    depth: int = Field(default=2, ge=1, le=1000, description="frames queued while busy")


Detector = Callable[[np.ndarray], FoundBlobs]


def detector(params: Params) -> Detector:
    """The function that finds ``params``' blobs in one frame's pixels (ValueError for bad settings)."""
    shape = {"min_area": params.min_area, "max_area": params.max_area}
    if params.method == "ir":
        settings = IrBlobParams(threshold=params.threshold, **shape)
        wide = IrBlobParams(threshold=params.threshold * MONO16_SCALE, **shape)
        return lambda data: detect_ir_blobs(as_grey(data), wide if data.dtype == np.uint16 else settings)
    if params.method == "log":
        log = LogBlobParams(min_sigma=params.min_sigma, max_sigma=params.max_sigma, threshold=params.log_threshold)
        return lambda data: _log_blobs(data, log)
    colour = ColourBlobParams(**shape)
    model = HueModel(params.hue_deg, params.hue_width_deg / colour.width, params.min_saturation, params.min_value)
    return lambda data: _colour_blobs(data, model, colour)


def _log_blobs(data: np.ndarray, settings: LogBlobParams) -> FoundBlobs:
    return detect_log_blobs(data[:, :, :3] if data.ndim == 3 else data, settings)


def _colour_blobs(data: np.ndarray, model: HueModel, settings: ColourBlobParams) -> FoundBlobs:
    if data.ndim != 3:
        encoding = "mono16" if data.dtype == np.uint16 else "mono8"
        raise UnusableFrame(f"the colour method needs bgr8 frames, not {encoding} (use method ir or log)")
    return detect_colour_blobs(np.ascontiguousarray(data[:, :, :3]), model, settings)


def as_message(header: Header, method: BlobMethod, found: FoundBlobs) -> Blobs:
    """``found`` in the frame with ``header`` as the message that carries it."""
    return Blobs(header=header, method=method, centroids=np.asarray(found.centroids, np.float64).reshape(-1, 2),
                 areas=found.area.astype(np.float32), radii=found.radius.astype(np.float32),
                 quality=np.nan_to_num(found.quality, nan=0.0).astype(np.float32), flags=found.flags.astype(np.uint8))


def run(node: Node, params: Params) -> None:
    try:
        find = detector(params)
    except ValueError as exc:
        raise NodeError(str(exc)) from exc
    out = node.publisher(node.keys.blobs(params.camera), Blobs, Role.RESULT)
    for image, found in detect_frames(node, params.camera, params.depth, find, lambda: FoundBlobs.from_rows([])):
        out.put(as_message(image.header, params.method, found))


def _check(params: Params) -> None:
    detector(params)


KIND = NodeKind(name="blobs", summary="bright spots (IR), scale-space or coloured blobs of a camera's frames",
                params=Params, run=run, inputs=("{camera}/image",), outputs=("{camera}/blobs",), check=_check)
