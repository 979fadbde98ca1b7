"""Per-frame detections in pixel coordinates of the source image.

Every detection message keeps the header of the image it was found in. Arrays are
aligned on their first axis: row ``i`` of every array describes detection ``i``. A frame
with nothing found still gets a message with zero rows, so consumers know it was seen.
"""

from __future__ import annotations

from typing import Annotated, Literal

import numpy as np
from pydantic import model_validator

from protocol.arrays import array_field
from protocol.message import Message


def _same_rows(message: Message, *names: str) -> None:
    rows = {name: len(getattr(message, name)) for name in names}
    if len(set(rows.values())) > 1:
        raise ValueError(f"arrays must have the same number of rows: {rows}")


class MarkerDetections(Message):
    """Square fiducial markers (ArUco / AprilTag) found in one image.

    ``corners``: (N, 4, 2) float32 px, in the order top-left, top-right, bottom-right,
    bottom-left of the marker as printed (OpenCV's order). ``quality``: (N,) float32,
    higher is better (the detector's decision margin or equivalent). ``side_m``: (N,)
    float32, each marker's configured side length in metres (0 when unknown).
    """

    SCHEMA = "artrack.MarkerDetections"
    VERSION = 1

    dictionary: str
    ids: Annotated[np.ndarray, array_field("int32", (None,))]
    corners: Annotated[np.ndarray, array_field("float32", (None, 4, 2))]
    quality: Annotated[np.ndarray, array_field("float32", (None,))]
    side_m: Annotated[np.ndarray, array_field("float32", (None,))]

    @model_validator(mode="after")
    def _aligned(self) -> MarkerDetections:
        _same_rows(self, "ids", "corners", "quality", "side_m")
        return self


BlobMethod = Literal["ir", "log", "colour"]

BLOB_MERGED, BLOB_OCCLUDED, BLOB_CLIPPED, BLOB_SPLIT = 1, 2, 4, 8
"""Bits of ``Blobs.flags``: two blobs run together; partly hidden or cut; touches the image border; one of the
two discs fitted to the merged or occluded blob in the row before the pair of ``BLOB_SPLIT`` rows."""


class Blobs(Message):
    """Blobs found in one camera image; ``header`` is the image's (``frame_id`` the camera).

    ``method``: the detector (``ir`` threshold and weighted centroid, ``log`` scale space,
    ``colour`` hue). ``centroids``: (N, 2) float64 px (x right, y down, centre of the top-left
    pixel at (0, 0)); ``areas``: (N,) float32 px^2; ``radii``: (N,) float32 px; ``quality``:
    (N,) float32 in [0, 1], higher is better; ``flags``: (N,) uint8, bits ``BLOB_MERGED``,
    ``BLOB_OCCLUDED``, ``BLOB_CLIPPED``, ``BLOB_SPLIT`` (0: one round, whole spot). The ``ir`` method follows a
    merged or occluded blob it could split with two ``BLOB_SPLIT`` rows, the centres of the two spots in it.
    """

    SCHEMA = "artrack.Blobs"
    VERSION = 1

    method: BlobMethod = "ir"
    centroids: Annotated[np.ndarray, array_field("float64", (None, 2))]
    areas: Annotated[np.ndarray, array_field("float32", (None,))]
    radii: Annotated[np.ndarray, array_field("float32", (None,))]
    quality: Annotated[np.ndarray, array_field("float32", (None,))]
    flags: Annotated[np.ndarray, array_field("uint8", (None,))]

    @model_validator(mode="after")
    def _aligned(self) -> Blobs:
        _same_rows(self, "centroids", "areas", "radii", "quality", "flags")
        return self


class Keypoints(Message):
    """Image features with optional descriptors; ``header`` is the image's (``frame_id`` the camera).

    ``points``: (N, 2) float32 px (x right, y down, centre of the top-left pixel at (0, 0));
    ``sizes`` (px), ``angles`` (deg, OpenCV's convention), ``responses``: (N,) float32;
    ``descriptors``: (N, D) uint8 for binary descriptors (ORB, TEBLID: D = 32; AKAZE: 61),
    compared by Hamming distance, or float32 (SIFT: D = 128) compared by L2 distance (``norm``
    says which), (N, 0) when none were computed. ``method`` names the detector (``"orb"``,
    ``"sift"``, ``"akaze"``, ``"harris"``, ``"shi_tomasi"``), ``descriptor_type`` the extractor
    (``"ORB"``, ``"TEBLID"``, ``"SIFT"``, ``"AKAZE"``, ``""``).

    Version 2 added ``method``; version 1 payloads (older recordings) still decode, with it empty.
    """

    SCHEMA = "artrack.Keypoints"
    VERSION = 2
    READS_OLDER = (1,)

    method: str = ""
    descriptor_type: str = ""
    points: Annotated[np.ndarray, array_field("float32", (None, 2))]
    sizes: Annotated[np.ndarray, array_field("float32", (None,))]
    angles: Annotated[np.ndarray, array_field("float32", (None,))]
    responses: Annotated[np.ndarray, array_field("float32", (None,))]
    descriptors: Annotated[np.ndarray, array_field(("uint8", "float32"), (None, None))]

    @model_validator(mode="after")
    def _aligned(self) -> Keypoints:
        _same_rows(self, "points", "sizes", "angles", "responses", "descriptors")
        return self

    @property
    def norm(self) -> Literal["hamming", "l2", ""]:
        """How descriptors compare: ``"hamming"`` (uint8, bits packed), ``"l2"`` (float32), ``""`` without any."""
        if self.descriptors.shape[1] == 0:
            return ""
        return "hamming" if self.descriptors.dtype == np.uint8 else "l2"
