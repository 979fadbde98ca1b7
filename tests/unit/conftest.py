"""Fixtures shared by the unit tests."""

import numpy as np
import pytest

from services.geometry.camera import CameraModel
from services.synthetic import make_scene


@pytest.fixture(scope="module")
def distorted_cameras() -> list[CameraModel]:
    """Three 1280x1024 cameras of the ``ir_rig`` scene (1 m baseline) with a stronger distortion than the scene's,
    tangential terms and k3 included, each camera's a little stronger than the one before."""
    scene = make_scene("ir_rig", camera_count=3, width=1280, height=1024, baseline=1.0)
    dist = np.array([-0.2, 0.08, 1e-3, -2e-3, -0.01])
    return [CameraModel(c.name, c.width, c.height, c.K, dist * (1.0 + 0.2 * k), c.T_rig_camera)
            for k, c in enumerate(scene.cameras)]
