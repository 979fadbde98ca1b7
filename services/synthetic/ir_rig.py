"""``ir_rig``: a calibrated multi-camera IR rig watching rigid bodies of retro-reflective spheres.

World = the rig frame: origin at the middle of the bar, axes as a camera looking forward
(x right along the bar, y down, z forward). With ``layout=bar`` (the default) camera ``cam<i>``
sits on the bar at x = (i - (n - 1) / 2) * baseline and is toed in to look at (0, 0, convergence).
With ``layout=arc`` the cameras stand on an arc around the volume's centre (0, 0, ``BODY_DEPTH_M``),
from ``-ARC_HALF_ANGLE_DEG`` to ``+ARC_HALF_ANGLE_DEG`` about the vertical, each at its own distance
from the centre (``ARC_DISTANCES_M``, in an order drawn from the seed) and raised by its own angle
(``ARC_ELEVATION_DEG``), each looking at the centre. A camera's ``T_rig_camera`` is its pose in the
world. Intrinsics differ slightly between cameras and, unless ``distortion`` is off, each has a small
plumb_bob distortion that the rendering goes through exactly (every pixel's ray is undistorted once,
at init).

Images are dark with the spheres as bright anti-aliased discs: a pixel is lit by the
fraction of its ray's angular footprint that falls inside the sphere's silhouette cone,
so the blob's size follows the sphere radius and depth. Bodies (see ``LAYOUTS``; their
frame is the one the layout coordinates are written in, origin near the spheres' centroid)
move smoothly about 1.8 to 2.6 m in front of the bar. Occlusion: time is cut into
half-second windows; in a fraction ``occlusion_rate`` of them one sphere, chosen per
window, is hidden from one camera (see ``occlusions``). ``spin`` multiplies the bodies' turning (the
amplitude of their rotation about their base orientation, and so their angular speed), so more of
their orientations pass in a sequence, among them those where two spheres of a body lie nearly along
a camera's line of sight and their blobs merge. ``strays`` stray reflections (see ``strays_at``)
are real 3D points, small spheres of ``STRAY_RADIUS_FRACTION`` of the bodies' radius that every
camera sees: each is lit in some ``STRAY_WINDOW_S`` windows of time (a fraction ``STRAY_PRESENT`` of
them, drawn from the seed per stray and window) and still during one, ``STRAY_OFFSET_M`` from the
centre of a body (drawn per window) as that body is in the middle of the window. Ground truth,
listed under every camera: ``("world", "body/<name>", T_world_body)`` for every body.

``motion=wand`` replaces the bodies by one calibration wand (body ``WAND_BODY``): spheres on
its x axis at ``wand_spheres`` metres from its first end (the origin), waved through the
volume in front of the bar (1.5 to 3.3 m deep, about the width the cameras see) with its direction
sweeping every way, as when calibrating a rig's extrinsics. ``motion=lframe`` shows one still
L-frame (body ``LFRAME_BODY``, spheres ``LFRAME``: the corner, the long arm's end on its x axis,
the short arm's end on its y axis; its z axis up) lying on a floor ``FLOOR_BELOW_M`` below the
bar, ``LFRAME_DEPTH_M`` ahead and turned ``LFRAME_YAW_DEG`` about the vertical: it sets a rig's
floor frame.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from services.geometry.camera import CameraModel, intrinsics, look_at, pixel_rays, project_points
from services.geometry.rotation import matrix_from_rotvec
from services.geometry.se3 import invert, transform_points
from services.geometry.trajectory import RigidPath, SinePath
from services.synthetic.base import SceneOptions, SyntheticScene, Truth, scene_rng
from services.synthetic.fixtures import Fixtures

LAYOUTS: dict[str, np.ndarray] = {
    "wand": np.array([[-0.065, -0.089, 0.0], [-0.012, 0.046, 0.0], [0.077, 0.043, 0.0]]),
    "tool": np.array([[0.032, -0.046, -0.012], [0.037, 0.033, 0.035], [-0.109, -0.053, -0.003],
                      [0.04, 0.067, -0.02]]),
    "head": np.array([[0.062, 0.022, 0.028], [0.059, -0.017, -0.031], [-0.008, 0.057, -0.011],
                      [-0.061, -0.1, 0.005], [-0.053, 0.038, 0.009]]),
    "glove": np.array([[0.054, -0.03, -0.013], [0.058, -0.092, -0.012], [-0.09, -0.009, -0.033],
                       [-0.044, 0.051, -0.018], [-0.015, 0.039, 0.041], [0.038, 0.041, 0.034]]),
}
"""Body name -> (N, 3) sphere centres in the body frame, metres. Within a body, spheres are at
least 50 mm apart and no two pairwise distances are within 4 mm; no triangle of spheres of one
body matches one of another body to within 5 mm (side by side)."""

WAND_BODY = "calibration_wand"
LFRAME_BODY = "ground_frame"
LFRAME = np.array([[0.0, 0.0, 0.0], [0.5, 0.0, 0.0], [0.0, 0.35, 0.0]])
FLOOR_BELOW_M, LFRAME_DEPTH_M, LFRAME_YAW_DEG = 0.7, 2.3, 20.0
MOTIONS = ("bodies", "wand", "lframe")
WAND_DEPTH_M, WAND_SPREAD_M = 2.4, (1.0, 0.65, 0.9)

HFOV_DEG = 56.0
BACKGROUND, SPHERE_PEAK = 12, 240
OCCLUSION_WINDOW_S = 0.5
BODY_DEPTH_M = 2.2
CAMERA_PURPOSE, PATH_PURPOSE, OCCLUSION_PURPOSE, STRAY_PURPOSE, ARC_PURPOSE = 100, 101, 102, 103, 104
CAMERA_LAYOUTS = ("bar", "arc")
ARC_HALF_ANGLE_DEG = 40.0
ARC_DISTANCES_M = (2.0, 3.2)
ARC_ELEVATION_DEG = (5.0, 25.0)
STRAY_WINDOW_S, STRAY_PRESENT, STRAY_RADIUS_FRACTION = 0.5, 0.6, 0.6
STRAY_OFFSET_M = (0.02, 0.08)


@dataclass(frozen=True)
class IrRigOptions(SceneOptions):
    """``camera_count`` cameras ``baseline`` metres apart, toed in to cross at ``convergence`` metres;
    ``distortion``: small plumb_bob distortion (else none); ``body_count`` bodies (the first of
    ``LAYOUTS``); ``sphere_radius``: metres; ``occlusion_rate``: fraction of half-second windows
    with one sphere hidden from one camera; ``motion``: ``bodies`` (the layouts moving about),
    ``wand`` (one calibration wand waved through the volume) or ``lframe`` (one L-frame lying still
    on the floor), ``body_count`` unused but for ``bodies``;
    ``wand_spheres``: the wand's sphere positions along it, metres from its first end (2 or 3,
    increasing, the first 0); ``layout``: ``bar`` (``baseline``, ``convergence``) or ``arc`` (the
    cameras around the volume, the module docstring); ``layouts``: the bodies shown by their names in
    ``LAYOUTS`` (default: the first ``body_count``); ``spin``: factor on the bodies' turning (its
    amplitude and angular speed); ``strays``: stray reflections (``strays_at``)."""

    camera_count: int = 2
    baseline: float = 0.3
    convergence: float = 2.5
    distortion: bool = True
    body_count: int = 3
    sphere_radius: float = 0.008
    occlusion_rate: float = 0.25
    motion: str = "bodies"
    wand_spheres: tuple[float, ...] = (0.0, 0.15, 0.5)
    layout: str = "bar"
    layouts: tuple[str, ...] = ()
    spin: float = 1.0
    strays: int = 0

    def __post_init__(self) -> None:
        super().__post_init__()
        self.check_int("camera_count", 2, 8)
        self.check_float("baseline", 0.01, 10.0)
        self.check_float("convergence", 0.5, 100.0)
        self.check_bool("distortion")
        self.check_int("body_count", 1, len(LAYOUTS))
        self.check_float("sphere_radius", 0.001, 0.05)
        self.check_float("occlusion_rate", 0.0, 1.0)
        if self.motion not in MOTIONS:
            raise ValueError(f"option motion={self.motion!r}: must be one of {', '.join(MOTIONS)}")
        try:
            spheres = tuple(float(x) for x in self.wand_spheres)
        except (TypeError, ValueError):
            spheres = ()
        if not 2 <= len(spheres) <= 3 or spheres[0] != 0.0 or np.diff(spheres).min() < 0.05 or spheres[-1] > 2.0:
            raise ValueError(f"option wand_spheres={self.wand_spheres!r}: must be 2 or 3 positions in metres, "
                             "the first 0, increasing by at least 0.05, at most 2")
        object.__setattr__(self, "wand_spheres", spheres)
        self.check_choice("layout", CAMERA_LAYOUTS)
        names = tuple(self.layouts) if isinstance(self.layouts, (tuple, list)) else (self.layouts,)
        if len(set(names)) != len(names) or not all(isinstance(n, str) and n in LAYOUTS for n in names):
            raise ValueError(f"option layouts={self.layouts!r}: must be distinct names among {', '.join(LAYOUTS)}")
        object.__setattr__(self, "layouts", names)
        self.check_float("spin", 0.0, 100.0)
        self.check_int("strays", 0, 16)


class IrRigScene(SyntheticScene):
    """Attributes: ``bodies`` (name -> (N, 3) sphere centres, body frame), ``sphere_radius`` (m);
    ``body_poses(index)`` and ``occlusions(index)`` give a frame's truth and hidden spheres."""

    name = "ir_rig"
    Options = IrRigOptions
    options: IrRigOptions

    def __init__(self, options: IrRigOptions | None = None):
        super().__init__(options)
        o = self.options
        self.sphere_radius = o.sphere_radius
        self.cameras = self.make_cameras()
        self.T_camera_world = {c.name: invert(c.T_rig_camera) for c in self.cameras}
        rng = scene_rng(o.seed, PATH_PURPOSE)
        self.bodies: dict[str, np.ndarray]
        self.paths: dict[str, RigidPath]
        if o.motion == "wand":
            self.bodies = {WAND_BODY: np.array([[x, 0.0, 0.0] for x in o.wand_spheres])}
            self.paths = {WAND_BODY: wand_path(rng, o.wand_spheres[-1])}
        elif o.motion == "lframe":
            self.bodies = {LFRAME_BODY: LFRAME}
            self.paths = {LFRAME_BODY: lframe_path()}
        else:
            shown = o.layouts or tuple(LAYOUTS)[:o.body_count]
            self.bodies = {name: LAYOUTS[name] for name in shown}
            self.paths = self.body_paths(rng)

    def fixtures(self) -> Fixtures:
        """The rig and the bodies the scene shows (``bodies``)."""
        return Fixtures(self.name, self.cameras, bodies=dict(self.bodies))

    def body_paths(self, rng: np.random.Generator) -> dict[str, RigidPath]:
        """The bodies' paths, side by side about ``BODY_DEPTH_M`` in front of the bar."""
        count = len(self.bodies)
        spread = np.linspace(-0.35, 0.35, count) if count > 1 else np.zeros(1)
        paths = {}
        for k, (name, x) in enumerate(zip(self.bodies, spread, strict=True)):
            position = SinePath.random(rng, (x, 0.1 * (-1) ** k, BODY_DEPTH_M), (0.25, 0.2, 0.35), (4.0, 10.0))
            turn = SinePath.random(rng, (0.0, 0.0, 0.0), (0.6, 0.6, 0.8), (5.0, 12.0))
            turn = dataclasses.replace(turn, amplitudes=turn.amplitudes * self.options.spin)
            paths[name] = RigidPath(position, turn, matrix_from_rotvec(rng.normal(0.0, 1.0, 3)))
        return paths

    @cached_property
    def rays(self) -> dict[str, np.ndarray]:
        """Camera name -> (H, W, 3) undistorted pixel rays, made at the first frame drawn (not to name cameras)."""
        return {c.name: pixel_rays(c.K, c.dist, c.width, c.height) for c in self.cameras}

    def make_cameras(self) -> tuple[CameraModel, ...]:
        """The rig's cameras: their poses (``camera_poses``), slightly different intrinsics, small distortion."""
        o = self.options
        rng = scene_rng(o.seed, CAMERA_PURPOSE)
        cameras = []
        for i, T_rig_camera in enumerate(self.camera_poses()):
            K = intrinsics(o.width, o.height, HFOV_DEG)
            K[[0, 1], [0, 1]] *= rng.uniform(0.99, 1.01, 2)
            K[:2, 2] += rng.uniform(-4.0, 4.0, 2)
            dist = (np.array([rng.uniform(-0.08, -0.04), rng.uniform(0.0, 0.02), *rng.uniform(-5e-4, 5e-4, 2), 0.0])
                    if o.distortion else np.zeros(5))
            cameras.append(CameraModel(f"cam{i}", o.width, o.height, K, dist, T_rig_camera))
        return tuple(cameras)

    def camera_poses(self) -> list[np.ndarray]:
        """(4, 4) ``T_rig_camera`` of each camera: toed in on the bar, or around the volume on the arc."""
        o = self.options
        up = np.array([0.0, -1.0, 0.0])
        if o.layout == "bar":
            target = np.array([0.0, 0.0, o.convergence])
            return [look_at(np.array([(i - (o.camera_count - 1) / 2) * o.baseline, 0.0, 0.0]), target, up)
                    for i in range(o.camera_count)]
        rng = scene_rng(o.seed, ARC_PURPOSE)
        centre = np.array([0.0, 0.0, BODY_DEPTH_M])
        azimuths = np.radians(np.linspace(-ARC_HALF_ANGLE_DEG, ARC_HALF_ANGLE_DEG, o.camera_count))
        distances = rng.permutation(np.linspace(*ARC_DISTANCES_M, o.camera_count))
        elevations = np.radians(rng.uniform(*ARC_ELEVATION_DEG, o.camera_count))
        poses = []
        for azimuth, distance, elevation in zip(azimuths, distances, elevations, strict=True):
            level = np.cos(elevation)
            back = np.array([np.sin(azimuth) * level, -np.sin(elevation), -np.cos(azimuth) * level])
            poses.append(look_at(centre + distance * back, centre, up))
        return poses

    def body_poses(self, index: int) -> dict[str, np.ndarray]:
        """Body name -> (4, 4) ``T_world_body`` in frame ``index``."""
        t = self.time_s(index)
        return {name: path.pose(t) for name, path in self.paths.items()}

    def occlusions(self, index: int) -> set[tuple[str, str, int]]:
        """``{(camera, body, sphere index)}`` hidden in frame ``index`` (at most one sphere)."""
        window = int(self.time_s(index) // OCCLUSION_WINDOW_S)
        rng = scene_rng(self.options.seed, OCCLUSION_PURPOSE, window)
        if rng.random() >= self.options.occlusion_rate:
            return set()
        body = list(self.bodies)[int(rng.integers(len(self.bodies)))]
        sphere = int(rng.integers(len(self.bodies[body])))
        return {(self.cameras[int(rng.integers(len(self.cameras)))].name, body, sphere)}

    def strays_at(self, index: int) -> np.ndarray:
        """(K, 3) world positions of the stray reflections lit in frame ``index`` (module docstring), K <= ``strays``.

        Stray ``k``'s windows are shifted by ``k / strays`` of a window, so the strays come and go at different
        times."""
        o = self.options
        found = []
        for k in range(o.strays):
            shift = k / o.strays * STRAY_WINDOW_S
            window = int((self.time_s(index) + shift) // STRAY_WINDOW_S)
            rng = scene_rng(o.seed, STRAY_PURPOSE, k, window)
            if rng.random() >= STRAY_PRESENT:
                continue
            body = list(self.bodies)[int(rng.integers(len(self.bodies)))]
            T = self.paths[body].pose((window + 0.5) * STRAY_WINDOW_S - shift)
            direction = rng.normal(0.0, 1.0, 3)
            centre = transform_points(T, self.bodies[body]).mean(axis=0)
            found.append(centre + rng.uniform(*STRAY_OFFSET_M) * direction / np.linalg.norm(direction))
        return np.array(found).reshape(-1, 3)

    def draw(self, index: int) -> tuple[dict[str, np.ndarray], dict[str, Truth]]:
        poses = self.body_poses(index)
        hidden = self.occlusions(index)
        truth = [("world", f"body/{name}", T) for name, T in poses.items()]
        spheres = [(name, j, centre) for name, T in poses.items()
                   for j, centre in enumerate(transform_points(T, self.bodies[name]))]
        strays = self.strays_at(index)
        stray_radius = STRAY_RADIUS_FRACTION * self.sphere_radius
        images = {}
        for camera in self.cameras:
            image = np.full((camera.height, camera.width), BACKGROUND, np.uint8)
            visible = [c for name, j, c in spheres if (camera.name, name, j) not in hidden]
            lit = np.concatenate([np.reshape(visible, (-1, 3)), strays])
            centres_cam = transform_points(self.T_camera_world[camera.name], lit)
            radii = np.r_[np.full(len(visible), self.sphere_radius), np.full(len(strays), stray_radius)]
            in_front = centres_cam[:, 2] > 2 * radii
            pixels = project_points(centres_cam[in_front], camera.K, camera.dist)
            for centre, radius, pixel in zip(centres_cam[in_front], radii[in_front], pixels, strict=True):
                draw_sphere(image, self.rays[camera.name], centre, float(radius), pixel, camera.K[0, 0])
            images[camera.name] = image
        return images, {camera.name: list(truth) for camera in self.cameras}


def lframe_path() -> RigidPath:
    """The L-frame lying still on the floor: body x and y in the floor, body z up (world -y)."""
    yaw = np.radians(LFRAME_YAW_DEG)
    R_world_body = matrix_from_rotvec(np.array([0.0, -yaw, 0.0])) @ np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0],
                                                                               [0.0, 1.0, 0.0]])
    still = np.zeros((1, 3))
    return RigidPath(SinePath(np.array([0.0, FLOOR_BELOW_M, LFRAME_DEPTH_M]), still, still, still),
                     SinePath(np.zeros(3), still, still, still), R_world_body)


def wand_path(rng: np.random.Generator, length: float) -> RigidPath:
    """A wand waved about: its middle sweeps the volume in front of the bar, its direction turns every way.

    The path moves the wand's origin (its first end); the offset keeps the wand's middle on the sweep.
    """
    middle = SinePath.random(rng, (0.0, 0.0, WAND_DEPTH_M), WAND_SPREAD_M, (3.0, 9.0), terms=3)
    turn = SinePath.random(rng, (0.0, 0.0, 0.0), (2.5, 2.5, 2.5), (4.0, 11.0), terms=2)
    R_base = matrix_from_rotvec(rng.normal(0.0, 1.0, 3))
    return WandPath(middle, turn, R_base, 0.5 * length)


@dataclass(frozen=True)
class WandPath(RigidPath):
    """A RigidPath whose ``position`` is the wand's middle, ``half_length`` metres along its x axis from the origin."""

    half_length: float = 0.0

    def pose(self, t: float) -> np.ndarray:
        """(4, 4) ``T_world_body`` at time ``t`` seconds (the body origin is the wand's first end)."""
        T = super().pose(t)
        T[:3, 3] -= self.half_length * T[:3, 0]
        return T


def draw_sphere(image: np.ndarray, rays: np.ndarray, centre_cam: np.ndarray, radius: float,
                pixel: np.ndarray, focal_px: float) -> None:
    """Brighten ``image`` in place where the sphere (centre (3,) camera frame, ``radius`` m) covers pixels.

    ``rays``: (H, W, 3) unit pixel rays; ``pixel``: the centre's projection (a window is drawn
    around it). Coverage ramps linearly over one pixel across the silhouette's edge.
    """
    distance = float(np.linalg.norm(centre_cam))
    direction = centre_cam / distance
    sin_radius = radius / distance
    half = int(np.ceil(1.2 * focal_px * sin_radius)) + 2
    h, w = image.shape
    x0, y0 = max(int(pixel[0]) - half, 0), max(int(pixel[1]) - half, 0)
    x1, y1 = min(int(pixel[0]) + half + 1, w), min(int(pixel[1]) + half + 1, h)
    if x0 >= x1 or y0 >= y1:
        return
    window_rays = rays[y0:y1, x0:x1].astype(np.float64)
    along = window_rays @ direction
    sin_off_axis = np.linalg.norm(window_rays - along[..., None] * direction, axis=2)
    coverage = np.clip((sin_radius - sin_off_axis) * focal_px + 0.5, 0.0, 1.0) * (along > 0)
    lit = (BACKGROUND + (SPHERE_PEAK - BACKGROUND) * coverage + 0.5).astype(np.uint8)
    np.maximum(image[y0:y1, x0:x1], lit, out=image[y0:y1, x0:x1])
