"""The ``ir_rig`` scene's calibration wand for tests: its blob centres (exact projections of the true sphere
centres through each camera's distortion plus Gaussian noise, in random order; spheres hidden by the scene's
occlusions or outside the image leave no blob), and the error of estimated extrinsics against the scene's."""

from __future__ import annotations

import numpy as np

from services.geometry.camera import project_points
from services.geometry.rotation import rotation_angle
from services.geometry.se3 import invert, transform_points
from services.synthetic import make_scene
from services.synthetic.ir_rig import WAND_BODY, IrRigScene


def wand_scene(camera_count: int, **options: object) -> IrRigScene:
    scene = make_scene("ir_rig", motion="wand", camera_count=camera_count, **options)
    assert isinstance(scene, IrRigScene)
    return scene


def wand_blobs(scene: IrRigScene, indices: range, sigma_px: float, seed: int = 0) -> list[list[np.ndarray]]:
    """``blobs[f][c]``: (N, 2) observed pixels of the wand's spheres in camera ``c`` at frame ``indices[f]``."""
    rng = np.random.default_rng(seed)
    frames = []
    for index in indices:
        spheres = transform_points(scene.body_poses(index)[WAND_BODY], scene.bodies[WAND_BODY])
        hidden = scene.occlusions(index)
        row = []
        for camera in scene.cameras:
            pixels = project_points(transform_points(invert(camera.T_rig_camera), spheres), camera.K, camera.dist)
            keep = [j for j, (u, v) in enumerate(pixels) if (camera.name, WAND_BODY, j) not in hidden
                    and 0 <= u <= camera.width - 1 and 0 <= v <= camera.height - 1]
            row.append(rng.permutation(pixels[keep] + rng.normal(0.0, sigma_px, (len(keep), 2))))
        frames.append(row)
    return frames


def extrinsic_errors(scene: IrRigScene, T_rig_camera: list[np.ndarray] | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(C,) position errors, mm, and (C,) rotation errors, degrees, of estimated ``T_rig_camera`` (C, 4, 4), in the
    scene's camera order and the first camera's frame, against the scene's cameras expressed in that frame."""
    T_first_rig = invert(scene.cameras[0].T_rig_camera)
    truth = [T_first_rig @ camera.T_rig_camera for camera in scene.cameras]
    pairs = list(zip(truth, T_rig_camera, strict=True))
    return (np.array([1000.0 * np.linalg.norm(t[:3, 3] - e[:3, 3]) for t, e in pairs]),
            np.degrees([rotation_angle(t[:3, :3], e[:3, :3]) for t, e in pairs]))
