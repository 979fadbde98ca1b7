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

The ``ir`` method's measurements, and the shape, waist test and split of merged blobs it shares with ``colour``, are
compiled (``measure_kernel``, ``merged_kernel``), loaded before the first frame; the launcher's preflight builds
them into numba's cache when it lacks them (``NodeKind.prepare``).

A frame the method cannot work on is counted as skipped and reported
(``services.runtime.frame_detection``). One frame may wait while another is searched (``depth``).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Annotated

import numpy as np
from pydantic import Field, model_validator

from protocol.detections import BlobMethod, Blobs
from protocol.keys import KeyName
from protocol.message import Header
from services.bus.pubsub import Role
from services.detection.blobs import measure_kernel, merged_kernel
from services.detection.blobs.bright import Blobs as FoundBlobs
from services.detection.blobs.bright import IrBlobParams, ShapeParams, detect_ir_blobs
from services.detection.blobs.colour import ColourBlobParams, HueModel, HueWindow, detect_colour_blobs
from services.detection.blobs.scale_space import LogBlobParams, detect_log_blobs
from services.detection.grey import MONO16_SCALE, as_grey
from services.runtime import compiled
from services.runtime.frame_detection import UnusableFrame, detect_frames
from services.runtime.kind import NodeKind
from services.runtime.node import Node
from services.runtime.params import Flat, NodeParams

EIGHT_BIT_MAX = 255.0


class Params(NodeParams):
    """Which camera, which detector and its settings.

    ``threshold`` is on the 8-bit scale whatever the frames: a mono16 frame is compared with 257 times it."""

    camera: KeyName = "cam0"
    method: BlobMethod = Field(default="ir", description="ir (threshold), log (scale space) or colour (hue)")
    ir: Annotated[IrBlobParams, Flat(label="ir")] = IrBlobParams()
    shape: Annotated[ShapeParams, Flat(label="ir, colour")] = ShapeParams()
    log: Annotated[LogBlobParams, Flat("log_", names={"min_sigma": "min_sigma", "max_sigma": "max_sigma"},
                                       label="log")] = LogBlobParams()
    hue: Annotated[HueWindow, Flat(label="colour")] = HueWindow()
    colour: Annotated[ColourBlobParams, Flat("colour_", label="colour")] = ColourBlobParams()
    depth: int = Field(default=2, ge=1, le=1000, description="frames queued while busy")

    @model_validator(mode="after")
    def _an_8_bit_threshold(self) -> Params:
        if self.ir.threshold > EIGHT_BIT_MAX:
            raise ValueError(f"threshold {self.ir.threshold} is above {EIGHT_BIT_MAX}: it is on the 8-bit scale "
                             "(mono16 frames are compared with 257 times it)")
        return self


Detector = Callable[[np.ndarray], FoundBlobs]


def detector(params: Params) -> Detector:
    """The function that finds ``params``' blobs in one frame's pixels."""
    if params.method == "ir":
        wide = params.ir.model_copy(update={"threshold": params.ir.threshold * MONO16_SCALE})
        return lambda data: detect_ir_blobs(as_grey(data), wide if data.dtype == np.uint16 else params.ir, params.shape)
    if params.method == "log":
        return lambda data: _log_blobs(data, params.log)
    model = params.hue.model(params.colour)
    return lambda data: _colour_blobs(data, model, params.colour, params.shape)


def _log_blobs(data: np.ndarray, settings: LogBlobParams) -> FoundBlobs:
    return detect_log_blobs(data[:, :, :3] if data.ndim == 3 else data, settings)


def _colour_blobs(data: np.ndarray, model: HueModel, settings: ColourBlobParams, shape: ShapeParams) -> FoundBlobs:
    if data.ndim != 3:
        encoding = "mono16" if data.dtype == np.uint16 else "mono8"
        raise UnusableFrame(f"the colour method needs bgr8 frames, not {encoding} (use method ir or log)")
    return detect_colour_blobs(np.ascontiguousarray(data[:, :, :3]), model, settings, shape)


def as_message(header: Header, method: BlobMethod, found: FoundBlobs) -> Blobs:
    """``found`` in the frame with ``header`` as the message that carries it."""
    return Blobs(header=header, method=method, centroids=np.asarray(found.centroids, np.float64).reshape(-1, 2),
                 areas=found.area.astype(np.float32), radii=found.radius.astype(np.float32),
                 quality=np.where(np.isnan(found.quality), 0.0, found.quality).astype(np.float32),
                 flags=found.flags.astype(np.uint8))


def run(node: Node, params: Params) -> None:
    find = detector(params)
    if params.method in ("ir", "colour"):
        _warm()
    out = node.publisher(node.keys.blobs(params.camera), Blobs, Role.RESULT)
    for image, found in detect_frames(node, params.camera, params.depth, find, lambda: FoundBlobs.from_rows([])):
        out.put(as_message(image.header, params.method, found))


def _warm() -> None:
    measure_kernel.warm()
    merged_kernel.warm()


def _prepare() -> None:
    compiled.prepare(_warm, "the blobs node's kernels")


KIND = NodeKind(name="blobs", summary="bright spots (IR), scale-space or coloured blobs of a camera's frames",
                params=Params, run=run, inputs=("{camera}/image",), outputs=("{camera}/blobs",), prepare=_prepare)
