"""Optical motion capture: the 3D points a rig triangulates from its cameras' ``protocol.detections.Blobs``.

Rows are aligned on the first axis, as in ``protocol.detections``: row ``i`` of every array
describes point ``i``; an instant with nothing found still gets a message with zero rows.
The bodies' poses travel as ``protocol.poses.Pose`` (``T_world_body``, frame ``world``, child
``body/<name>``), one key per body.
"""

from __future__ import annotations

from typing import Annotated

import numpy as np
from pydantic import model_validator

from protocol.arrays import array_field
from protocol.detections import _same_rows
from protocol.message import Message


class Points3D(Message):
    """Points a rig triangulated at one instant, in ``header.frame_id`` (``world``, the rig frame).

    ``points``: (N, 3) float64 m; ``residual_px``: (N,) float32, RMS reprojection error over the
    views; ``views``: (N,) uint8, cameras that saw the point; ``covariances``: (N, 3, 3) float64
    m^2; ``body``: (N,) int32, index into ``bodies`` of the body the point was matched to, -1 for
    an unlabelled point; ``bodies``: the names the indices refer to.
    """

    SCHEMA = "artrack.Points3D"
    VERSION = 1

    bodies: tuple[str, ...] = ()
    points: Annotated[np.ndarray, array_field("float64", (None, 3))]
    residual_px: Annotated[np.ndarray, array_field("float32", (None,))]
    views: Annotated[np.ndarray, array_field("uint8", (None,))]
    covariances: Annotated[np.ndarray, array_field("float64", (None, 3, 3))]
    body: Annotated[np.ndarray, array_field("int32", (None,))]

    @model_validator(mode="after")
    def _aligned(self) -> Points3D:
        _same_rows(self, "points", "residual_px", "views", "covariances", "body")
        if len(self.body) and not (int(self.body.min()) >= -1 and int(self.body.max()) < len(self.bodies)):
            raise ValueError(f"body indices must be -1 or index one of the {len(self.bodies)} bodies")
        return self
