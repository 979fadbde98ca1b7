"""``pattern``: the simplest scene, a moving test pattern with no ground truth.

A dim vertical gradient with a bright disc travelling along a Lissajous path (its phases
drawn from the seed) and the frame number printed in a corner; one camera, ``cam0``, 60 degrees
horizontal field of view. Good for checking that frames flow; it gives trackers nothing to track.
"""

from __future__ import annotations

import cv2
import numpy as np

from services.geometry.camera import CameraModel, intrinsics
from services.synthetic.base import SyntheticScene, Truth, scene_rng

PHASE_PURPOSE = 100
SUBPIXEL_BITS = 4
"""cv2.circle's ``shift``: the disc centre is placed to 1/16 px."""


class PatternScene(SyntheticScene):
    name = "pattern"

    def __init__(self, options=None):
        super().__init__(options)
        o = self.options
        K = intrinsics(o.width, o.height, 60.0)
        self.cameras = (CameraModel("cam0", o.width, o.height, K, np.zeros(5), np.eye(4)),)
        self._phase = scene_rng(o.seed, PHASE_PURPOSE).uniform(0, 2 * np.pi, 2)
        self._background = np.broadcast_to(
            np.linspace(20, 90, o.height, dtype=np.float32)[:, None], (o.height, o.width)).astype(np.uint8)

    def disc_centre(self, index: int) -> tuple[float, float]:
        """Pixel centre ``(u, v)`` of the disc in frame ``index``."""
        t, w, h = self.time_s(index), self.options.width, self.options.height
        return (w / 2 + 0.35 * w * np.sin(1.3 * t + self._phase[0]),
                h / 2 + 0.35 * h * np.sin(2.1 * t + self._phase[1]))

    def draw(self, index: int) -> tuple[dict[str, np.ndarray], dict[str, Truth]]:
        image = self._background.copy()
        u, v = self.disc_centre(index)
        scale = 1 << SUBPIXEL_BITS
        radius = max(4, self.options.height // 24) * scale
        cv2.circle(image, (round(u * scale), round(v * scale)), radius, 250, -1, cv2.LINE_AA, SUBPIXEL_BITS)
        cv2.putText(image, f"{index:06d}", (8, self.options.height - 10), cv2.FONT_HERSHEY_SIMPLEX, 0.6, 200, 1,
                    cv2.LINE_AA)
        return {"cam0": image}, {"cam0": []}
