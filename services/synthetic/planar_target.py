"""``planar_target``: a feature-rich printed image target seen by one hand-held camera.

Target frame: origin at the target's centre, x right, y up, z out of the target towards the
camera (as the ArUco marker frame). The texture (``texture``, (h, w) uint8, procedural and
seeded) covers ``size_m`` = (width, height) metres; around it the world is flat grey.

The camera (cam0; the rig is the camera, ``T_rig_camera`` = identity, no distortion) sways
between 0.7 and 2.4 target widths from the target while looking at it. Over time the light
changes (a global gain and a gradient across the image, both slowly varying) and the focus
is fixed at the middle distance, so nearer and farther views are defocused (a gaussian blur
whose sigma grows with the distance from the focus in dioptres). With ``motion=static`` the camera
holds its pose of frame 0 (the light still changes), to measure how much a still target's pose
shakes. Ground truth:
``("cam0", "target", T_cam0_target)`` in every frame.

Its fixture (``fixtures``) is the printed target: the texture, ``target_width`` metres wide, named
``planar_target``, in the scene's target frame, so a tracker's poses of it score against the truth as
they are.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from services.geometry.camera import CameraModel, intrinsics
from services.geometry.se3 import invert
from services.synthetic.base import SceneOptions, SyntheticScene, Truth, scene_rng
from services.synthetic.fixtures import Fixtures, ImageTarget
from services.synthetic.imaging import Lighting, gaussian_blur
from services.synthetic.paths import plane_viewing_path
from services.synthetic.plane import PlaneTexture
from services.synthetic.texture import procedural_texture

HFOV_DEG = 56.0
OUTSIDE_GREY = 110
PATH_PURPOSE, TEXTURE_PURPOSE, LIGHT_PURPOSE = 100, 101, 102
MOTIONS = ("sway", "static")


@dataclass(frozen=True)
class PlanarTargetOptions(SceneOptions):
    """``target_width``/``target_height``: metres; ``texture_px``: texels across the target;
    ``lighting``: amplitude of the slow gain change (0 = constant light); ``defocus``: blur
    sigma in pixels per dioptre away from the focus distance (0 = always sharp); ``motion``: ``sway``
    (the hand-held camera moving about) or ``static`` (the camera still at its pose of frame 0)."""

    target_width: float = 0.297
    target_height: float = 0.21
    texture_px: int = 1024
    lighting: float = 0.25
    defocus: float = 0.6
    motion: str = "sway"

    def __post_init__(self) -> None:
        super().__post_init__()
        self.check_float("target_width", 0.0, 100.0, low_open=True)
        self.check_float("target_height", 0.0, 100.0, low_open=True)
        self.check_int("texture_px", 64, 8192)
        self.check_float("lighting", 0.0, 0.9)
        self.check_float("defocus", 0.0, 20.0)
        if self.motion not in MOTIONS:
            raise ValueError(f"option motion={self.motion!r}: must be one of {', '.join(MOTIONS)}")


class PlanarTargetScene(SyntheticScene):
    """Attributes: ``texture`` ((h, w) uint8), ``size_m`` ((width, height) metres) and ``target``
    (its PlaneTexture); ``camera_pose(index)`` gives ``T_target_cam0``."""

    name = "planar_target"
    Options = PlanarTargetOptions
    options: PlanarTargetOptions

    def __init__(self, options: PlanarTargetOptions | None = None):
        super().__init__(options)
        o = self.options
        self.size_m = (o.target_width, o.target_height)
        w = o.target_width
        near, far = 0.7 * w, 2.4 * w
        self.focus_m = (near + far) / 2
        self.path = plane_viewing_path(scene_rng(o.seed, PATH_PURPOSE), near=near, far=far,
                                       lateral=(0.7 * w, 0.5 * w), wander=(0.15 * w, 0.1 * w), roll=0.5)
        self.light = Lighting(scene_rng(o.seed, LIGHT_PURPOSE), o.lighting)
        K = intrinsics(o.width, o.height, HFOV_DEG)
        self.cameras = (CameraModel("cam0", o.width, o.height, K, np.zeros(5), np.eye(4)),)

    @cached_property
    def texture(self) -> np.ndarray:
        """(H, W) uint8, the target's image, drawn on first use (a scene built for its cameras alone never draws
        it)."""
        o = self.options
        texture_height = max(round(o.texture_px * o.target_height / o.target_width), 1)
        return procedural_texture(scene_rng(o.seed, TEXTURE_PURPOSE), o.texture_px, texture_height)

    @cached_property
    def target(self) -> PlaneTexture:
        """The target's plane, ``size_m`` (width, height) metres, textured with ``texture``."""
        return PlaneTexture(self.texture, *self.size_m)

    def fixtures(self) -> Fixtures:
        """The rig and the printed target: the texture, ``target_width`` wide, named after the scene."""
        return Fixtures(self.name, self.cameras, target=ImageTarget(self.name, self.texture, self.size_m[0]))

    def camera_pose(self, index: int) -> np.ndarray:
        """(4, 4) ``T_target_cam0`` of frame ``index`` (of frame 0 for ``motion=static``)."""
        return self.path.pose(0.0 if self.options.motion == "static" else self.time_s(index))

    def draw(self, index: int) -> tuple[dict[str, np.ndarray], dict[str, Truth]]:
        camera = self.cameras[0]
        T_cam_target = invert(self.camera_pose(index))
        image = self.target.warp(camera.K, T_cam_target, (camera.width, camera.height), border_value=OUTSIDE_GREY)
        distance = T_cam_target[2, 3]
        image = gaussian_blur(image, self.options.defocus * abs(1.0 / distance - 1.0 / self.focus_m))
        image = self.light.apply(image, self.time_s(index))
        return {"cam0": image}, {"cam0": [("cam0", "target", T_cam_target)]}
