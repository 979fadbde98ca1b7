"""``room``: a textured room with boxes on the floor, seen by one camera walking around inside.

World = room frame, z up: origin at the centre of the floor, x along the room's length,
y across it; the room spans |x| <= length/2, |y| <= width/2, 0 <= z <= height. Every
face (floor, ceiling, four walls, the visible sides and top of each box) carries its own
procedural texture; the north wall (y = +width/2) also carries a chessboard poster
(``CHECKER_INNER`` inner corners, ``CHECKER_SQUARE_M`` squares, see ``checker_corners``).

With the ``marker`` option an ArUco marker hangs on the north wall beside the poster (``MARKER_CENTRE_M``),
on a white sheet a quarter of its side wider on every side, ``MARKER_OFFSET_M`` in front of the wall; its
frame is ArUco's (origin at its centre, x right, y up, z out of the wall into the room). With seed 0
the camera sees it whole in frames 45-121 and 191-264 (from two sides of the room), 616-701 and 739-826.

With ``path="loop"`` the camera goes round the room instead, once every ``loop_s`` seconds: its eye on an
ellipse (``LOOP_RADII_M``) about the room's centre at ``LOOP_EYE_HEIGHT_M``, looking outwards at the walls
(``LOOP_LOOK_AHEAD_RAD`` ahead of straight out, ``LOOP_PITCH_RAD`` down), so that after ``loop_s`` seconds it
is back where it began, looking the same way: a closed loop whose end sees what its start saw.

The camera (cam0; the rig is the camera, ``T_rig_camera`` = identity, no distortion) walks
over the free middle of the room at eye height 1.35 to 1.65 m (above every box), looking
around with a slowly swinging heading and pitch: translation and rotation together, as a
SLAM sequence needs. Ground truth: ``("world", "cam0", T_world_cam0)`` in every frame and, with the
marker, ``("cam0", "marker/<id>", T_cam0_marker)`` in the frames where its four corners are in front of
the camera and inside the image (as the ``markers`` scene gives it).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import cv2
import numpy as np

from services.detection.markers.detector import DICTIONARY_NAMES, aruco_dictionary
from services.geometry.camera import CameraModel, intrinsics, look_at, project_points
from services.geometry.se3 import invert, make_transform, transform_points
from services.geometry.trajectory import SinePath
from services.synthetic.base import SceneOptions, SyntheticScene, Truth, scene_rng
from services.synthetic.compositing import Face, render_faces
from services.synthetic.fixtures import Fixtures
from services.synthetic.markers import inside_image
from services.synthetic.plane import PlaneTexture, rectangle_corners, texel_from_plane
from services.synthetic.texture import procedural_texture

HFOV_DEG = 64.0
TEXELS_PER_M = 200
LENGTH_M, WIDTH_M, HEIGHT_M = 6.0, 5.0, 2.7
BOXES = (
    ((-2.1, -1.6), (0.9, 0.7, 0.9)),
    ((2.0, -1.5), (1.0, 0.6, 0.5)),
    ((1.9, 1.4), (0.6, 0.6, 1.0)),
    ((-2.2, 1.5), (0.8, 0.5, 0.7)),
)
"""(floor centre (x, y), size (x, y, z)) of each box, metres; they are axis aligned."""
CHECKER_INNER = (9, 6)
CHECKER_SQUARE_M = 0.1
CHECKER_CENTRE_M = (0.0, 1.5)
"""Where the poster's centre is on the north wall: (x, z)."""
MARKER_CENTRE_M = (0.9, 1.0)
"""Where the marker's centre is on the north wall: (x, z), right of the poster."""
MARKER_QUIET_ZONE = 0.25
"""White margin around the marker, in marker sides, on every side."""
MARKER_OFFSET_M = 0.002
"""How far the marker's sheet stands in front of the wall."""
MARKER_CELL_TEXELS = 32
"""Texels per marker bit of the sheet's texture."""
BACKGROUND = 0
UP = np.array([0.0, 0.0, 1.0])
SIDE_NORMALS = np.array([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, -1.0, 0.0]])
TEXTURE_PURPOSE, PATH_PURPOSE = 100, 101
PATHS = ("sine", "loop")
LOOP_RADII_M = (1.3, 1.0)
"""Half axes (x, y) of the loop's ellipse, metres."""
LOOP_EYE_HEIGHT_M = 1.5
LOOP_LOOK_AHEAD_RAD = 0.3
"""How far the loop's camera looks ahead of straight out from the room's centre (towards its motion)."""
LOOP_PITCH_RAD = -0.3


@dataclass(frozen=True)
class RoomOptions(SceneOptions):
    """``boxes``: how many of the room's boxes to place (0 to 4); ``marker``: hang an ArUco marker on the
    north wall (off by default); ``marker_dictionary``: its cv2.aruco predefined dictionary;
    ``marker_id``: its id there; ``marker_length``: side of its black square, metres. ``path``: ``"sine"``
    (the default walk) or ``"loop"`` (round the room once every ``loop_s`` seconds)."""

    boxes: int = 4
    marker: bool = False
    marker_dictionary: str = "DICT_4X4_50"
    marker_id: int = 0
    marker_length: float = 0.3
    path: str = "sine"
    loop_s: float = 20.0

    def __post_init__(self) -> None:
        super().__post_init__()
        self.check_int("boxes", 0, len(BOXES))
        self.check_bool("marker")
        self.check_choice("marker_dictionary", DICTIONARY_NAMES)
        self.check_int("marker_id", 0, len(aruco_dictionary(self.marker_dictionary).bytesList) - 1)
        self.check_float("marker_length", 0.0, 1.0, low_open=True)
        self.check_choice("path", PATHS)
        self.check_float("loop_s", 1.0, 3600.0)


def face_pose(centre: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """(4, 4) ``T_world_face`` of a face at ``centre`` whose visible side faces ``normal`` (z up world).

    Walls and box sides are upright (face y = world z); floors and box tops have face x = world x
    and ceilings face x = world x seen from below.
    """
    normal = np.asarray(normal, dtype=np.float64)
    if abs(normal @ UP) > 0.5:
        x_axis = np.array([1.0, 0.0, 0.0])
        y_axis = np.cross(normal, x_axis)
    else:
        x_axis, y_axis = np.cross(UP, normal), UP
    return make_transform(np.column_stack([x_axis, y_axis, normal]), centre)


class RoomScene(SyntheticScene):
    """Attributes: ``faces`` (list of ``Face``, world frame), ``checker_corners`` ((N, 3) world,
    the poster's inner corners row by row, left to right, from its top-left one) and, with the marker,
    ``T_world_marker`` ((4, 4), None without) and ``marker_corners`` ((4, 3) in the marker frame, ArUco
    order TL, TR, BR, BL); ``camera_pose(index)`` gives ``T_world_cam0``."""

    name = "room"
    Options = RoomOptions
    options: RoomOptions

    def __init__(self, options: RoomOptions | None = None):
        super().__init__(options)
        o = self.options
        north = next((centre, normal, size) for name, centre, normal, size in self.layout() if name == "wall_north")
        self.checker_corners = transform_points(face_pose(*north[:2]), checker_layout(north[2])[2])
        self.T_world_marker: np.ndarray | None = None
        self.marker_corners = rectangle_corners(o.marker_length, o.marker_length)
        if o.marker:
            self.T_world_marker = face_pose(np.array([MARKER_CENTRE_M[0], WIDTH_M / 2 - MARKER_OFFSET_M,
                                                      MARKER_CENTRE_M[1]]), np.array([0.0, -1.0, 0.0]))
        path_rng = scene_rng(o.seed, PATH_PURPOSE)
        self.eye = SinePath.random(path_rng, (0.0, 0.0, 1.5), (1.2, 0.9, 0.15), (8.0, 16.0))
        self.heading = SinePath.random(path_rng, (0.0, -0.25), (2.5, 0.2), (14.0, 30.0))
        """(yaw about world z from +x, pitch) in radians."""
        self.cameras = (CameraModel("cam0", o.width, o.height, intrinsics(o.width, o.height, HFOV_DEG),
                                    np.zeros(5), np.eye(4)),)

    @cached_property
    def faces(self) -> list[Face]:
        """The textured faces, drawn on first use: a scene built for its cameras or fixtures alone (as the
        launcher's checks build it) never draws them, which takes about half a second."""
        rng = scene_rng(self.options.seed, TEXTURE_PURPOSE)
        faces = []
        for name, centre, normal, size in self.layout():
            image = procedural_texture(rng, *(texels(side) for side in size))
            if name == "wall_north":
                paint_checker(image, size)
            faces.append(Face(name, face_pose(centre, normal), PlaneTexture(image, *size)))
        if self.T_world_marker is not None:
            faces.append(Face("marker", self.T_world_marker, marker_sheet(self.options)))
        return faces

    def fixtures(self) -> Fixtures:
        """The rig and, with the marker, its side and dictionary, as a marker tracker takes them."""
        o = self.options
        settings = {"marker_length": o.marker_length, "dictionary": o.marker_dictionary} if o.marker else {}
        return Fixtures(self.name, self.cameras, settings=settings)

    def layout(self) -> list[tuple[str, np.ndarray, np.ndarray, tuple[float, float]]]:
        """(name, centre, normal of the visible side, (width, height)) of every face."""
        lx, ly, h = LENGTH_M / 2, WIDTH_M / 2, HEIGHT_M
        faces = [
            ("floor", np.array([0.0, 0.0, 0.0]), UP, (LENGTH_M, WIDTH_M)),
            ("ceiling", np.array([0.0, 0.0, h]), -UP, (LENGTH_M, WIDTH_M)),
            ("wall_north", np.array([0.0, ly, h / 2]), np.array([0.0, -1.0, 0.0]), (LENGTH_M, h)),
            ("wall_south", np.array([0.0, -ly, h / 2]), np.array([0.0, 1.0, 0.0]), (LENGTH_M, h)),
            ("wall_east", np.array([lx, 0.0, h / 2]), np.array([-1.0, 0.0, 0.0]), (WIDTH_M, h)),
            ("wall_west", np.array([-lx, 0.0, h / 2]), np.array([1.0, 0.0, 0.0]), (WIDTH_M, h)),
        ]
        for b, ((x, y), box) in enumerate(BOXES[:self.options.boxes]):
            size = np.array(box)
            middle = np.array([x, y, size[2] / 2])
            faces.append((f"box{b}_top", middle + UP * size[2] / 2, UP, (size[0], size[1])))
            for k, normal in enumerate(SIDE_NORMALS):
                across = size[1] if normal[0] else size[0]
                faces.append((f"box{b}_side{k}", middle + normal * size / 2, normal, (across, size[2])))
        return faces

    def camera_pose(self, index: int) -> np.ndarray:
        """(4, 4) ``T_world_cam0`` of frame ``index``."""
        t = self.time_s(index)
        if self.options.path == "loop":
            angle = 2 * np.pi * t / self.options.loop_s
            eye = np.array([LOOP_RADII_M[0] * np.cos(angle), LOOP_RADII_M[1] * np.sin(angle), LOOP_EYE_HEIGHT_M])
            yaw, pitch = angle + LOOP_LOOK_AHEAD_RAD, LOOP_PITCH_RAD
        else:
            eye = self.eye(t)
            yaw, pitch = self.heading(t)
        direction = np.array([np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw), np.sin(pitch)])
        return look_at(eye, eye + direction, UP)

    def draw(self, index: int) -> tuple[dict[str, np.ndarray], dict[str, Truth]]:
        camera = self.cameras[0]
        T_world_cam = self.camera_pose(index)
        image = render_faces(self.faces, camera.K, invert(T_world_cam), (camera.width, camera.height), BACKGROUND)
        truth: Truth = [("world", "cam0", T_world_cam)]
        if self.T_world_marker is not None:
            T_cam_marker = invert(T_world_cam) @ self.T_world_marker
            corners = transform_points(T_cam_marker, self.marker_corners)
            if np.all(corners[:, 2] > 0) and inside_image(project_points(corners, camera.K), camera):
                truth.append(("cam0", f"marker/{self.options.marker_id}", T_cam_marker))
        return {"cam0": image}, {"cam0": truth}


def marker_sheet(options: RoomOptions) -> PlaneTexture:
    """The marker ``options`` name on its white sheet (``MARKER_QUIET_ZONE`` wide), centred in the texture."""
    dictionary = aruco_dictionary(options.marker_dictionary)
    cells = dictionary.markerSize + 2
    marker_texels = cells * MARKER_CELL_TEXELS
    margin = round(MARKER_QUIET_ZONE * marker_texels)
    image = np.full((marker_texels + 2 * margin,) * 2, 255, np.uint8)
    image[margin:margin + marker_texels, margin:margin + marker_texels] = cv2.aruco.generateImageMarker(
        dictionary, options.marker_id, marker_texels, borderBits=1)
    side = options.marker_length * image.shape[0] / marker_texels
    return PlaneTexture(image, side, side)


def texels(side_m: float) -> int:
    """Texels of a face's texture along a side of ``side_m`` metres."""
    return max(round(side_m * TEXELS_PER_M), 1)


def checker_layout(size: tuple[float, float]) -> tuple[np.ndarray, tuple[int, int], np.ndarray]:
    """The chessboard poster of the north wall, whose texture covers ``size`` (width, height) metres: its
    (H, W) uint8 texels, the texel ``(left, top)`` of its top-left corner in the wall's texture, and its inner
    corners, (N, 3) in the wall's face frame, row by row from the top left."""
    columns, rows = CHECKER_INNER
    square = round(CHECKER_SQUARE_M * TEXELS_PER_M)
    poster = np.full(((rows + 3) * square, (columns + 3) * square), 255, np.uint8)
    for r in range(rows + 1):
        for c in range(columns + 1):
            if (r + c) % 2 == 0:
                poster[(r + 1) * square:(r + 2) * square, (c + 1) * square:(c + 2) * square] = 0
    from_plane = texel_from_plane((texels(size[1]), texels(size[0])), *size)
    centre = from_plane @ (CHECKER_CENTRE_M[0], CHECKER_CENTRE_M[1] - HEIGHT_M / 2, 1.0)
    # texel (i, j) spans [i - 0.5, i + 0.5]: put the poster's edges on texel edges
    left = int(round(centre[0] + 0.5 - poster.shape[1] / 2))
    top = int(round(centre[1] + 0.5 - poster.shape[0] / 2))
    cs, rs = np.meshgrid(np.arange(columns), np.arange(rows))
    corners = np.stack([left + (cs.ravel() + 2) * square - 0.5, top + (rs.ravel() + 2) * square - 0.5,
                        np.ones(cs.size)], axis=1)
    plane = np.linalg.solve(from_plane, corners.T).T
    return poster, (left, top), np.column_stack([plane[:, :2], np.zeros(len(plane))])


def paint_checker(image: np.ndarray, size: tuple[float, float]) -> None:
    """Paint the chessboard poster (``checker_layout``) into the north wall's texture ``image``, which covers
    ``size`` metres."""
    poster, (left, top), _ = checker_layout(size)
    image[top:top + poster.shape[0], left:left + poster.shape[1]] = poster
