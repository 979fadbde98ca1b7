"""OpenCV's box pair (``object_box_opencv``: ``box.png`` and ``box_in_scene.png``, grey) and the box's
outline in the scene, checked by hand (the data set has no ground truth).

Pixels: the centre of the top-left pixel at (0, 0).
"""

from __future__ import annotations

import cv2
import numpy as np

from tests.data import data_dir

HAND_CHECKED_TOP_LEFT = (118.5, 161.5)
"""The box's top-left corner in box_in_scene.png, read off a 10x zoom (the right corners are occluded)."""
OUTLINE = np.array([HAND_CHECKED_TOP_LEFT, (286.0, 175.0), (270.0, 298.5), (89.0, 271.5)])
"""(4, 2) the box face's outline TL, TR, BR, BL: the top-left corner as read, the others where its visible
edges lead."""
SCENE_FOV_DEG = 60.0
"""The horizontal field of view assumed for the uncalibrated scene image."""


def box_images() -> tuple[np.ndarray, np.ndarray]:
    """``(box, scene)``: the (223, 324) template and the (384, 512) scene, uint8; skips the test when the
    data set is absent."""
    folder = data_dir("object_box_opencv")
    return (cv2.imread(str(folder / "box.png"), cv2.IMREAD_GRAYSCALE),
            cv2.imread(str(folder / "box_in_scene.png"), cv2.IMREAD_GRAYSCALE))


def box_outline(H: np.ndarray, box_shape: tuple[int, ...]) -> np.ndarray:
    """(4, 2) the template's outer corners TL, TR, BR, BL mapped into the scene by the (3, 3) homography
    ``H`` (template pixel -> scene pixel), for a template of ``box_shape`` (H, W)."""
    h, w = box_shape[:2]
    corners = np.array([[-0.5, -0.5], [w - 0.5, -0.5], [w - 0.5, h - 0.5], [-0.5, h - 0.5]]).reshape(-1, 1, 2)
    return cv2.perspectiveTransform(corners, H).reshape(4, 2)
