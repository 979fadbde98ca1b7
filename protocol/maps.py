"""3D points: triangulated markers, SLAM map points."""

from __future__ import annotations

from typing import Annotated

import numpy as np
from pydantic import model_validator

from protocol.arrays import array_field
from protocol.message import Message


class PointCloud(Message):
    """3D points in ``header.frame_id``.

    ``points``: (N, 3) float32 metres; ``ids``: (N,) int64 stable point ids (map point
    ids for SLAM); ``colors``: (N, 3) uint8 BGR, or (0, 3) when the points have no colour.
    """

    SCHEMA = "artrack.PointCloud"
    VERSION = 1

    points: Annotated[np.ndarray, array_field("float32", (None, 3))]
    ids: Annotated[np.ndarray, array_field("int64", (None,))]
    colors: Annotated[np.ndarray, array_field("uint8", (None, 3))]

    @model_validator(mode="after")
    def _aligned(self) -> PointCloud:
        if len(self.ids) != len(self.points) or len(self.colors) not in (0, len(self.points)):
            raise ValueError(
                f"{len(self.points)} points need as many ids (got {len(self.ids)}) "
                f"and as many colours or none (got {len(self.colors)})"
            )
        return self
