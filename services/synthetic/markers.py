"""``markers``: a board of ArUco markers seen by one hand-held camera.

The markers lie in a grid on a white board (plane frame = board frame: origin at the board
centre, x right, y up, z out of the board towards the camera). Each marker's frame is the
board frame moved to the marker's centre, as OpenCV's ArUco defines it. Neighbouring
markers are two side lengths apart centre to centre, so every marker has a white quiet zone
of at least half a side. Outside the board the world is flat grey.

The camera (cam0; the rig is the camera, ``T_rig_camera`` = identity, no distortion) sways
between about 3.2 and 16 marker lengths from the board (option ``distance``) while looking at
it, so a marker spans about 6 % to 30 % of the image width and at close range some markers
leave the view. Each pixel is one bilinear sample of the board's mip level nearest the pixel's
footprint, whose aliasing moves a side's edge by up to a few hundredths of a pixel from frame to
frame (no bias); ``supersample`` > 1 averages that many samples per pixel and axis (an area
sample of the board), for accuracy tests that need the edges exact to a thousandth of a pixel.
With ``lighting`` > 0 the light changes over time (a global gain and a gradient
across the image, as in ``planar_target``); the board is then printed darker, its white at
``255 / (1 + 2 * lighting)``, so that the brightest light does not saturate it (a white clipped
at 255 would move every edge: an overexposed black square looks smaller). The dictionary may be
any predefined one, ArUco or AprilTag: a marker is drawn as ``cv2.aruco.generateImageMarker``
draws it (one black border cell around its bits), and the board's white around it is its quiet
zone.
Ground truth: ``("cam0", "marker/<id>", T_cam0_marker)`` for every marker whose four corners
are in front of the camera and inside the image (0 <= u <= W - 1, 0 <= v <= H - 1).
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass

import cv2
import numpy as np

from services.detection.markers.detector import DICTIONARY_NAMES, aruco_dictionary
from services.geometry.camera import CameraModel, intrinsics, project_points
from services.geometry.se3 import invert, make_transform, transform_points
from services.synthetic.base import SceneOptions, SyntheticScene, Truth, scene_rng
from services.synthetic.fixtures import Fixtures, MarkerLayout
from services.synthetic.imaging import Lighting
from services.synthetic.paths import plane_viewing_path
from services.synthetic.plane import PlaneTexture, rectangle_corners

HFOV_DEG = 56.0
CELL_TEXELS = 40
"""Texels per marker bit at full resolution."""
BOARD_WHITE, OUTSIDE_GREY = 255, 96
PATH_PURPOSE, LIGHT_PURPOSE = 100, 101


@dataclass(frozen=True)
class MarkersOptions(SceneOptions):
    """``dictionary``: a cv2.aruco predefined dictionary name; ``ids``: the markers, row by row from
    the top left; ``marker_length``: side of a marker's black square, metres; ``distance``: the
    nearest and farthest the camera comes to the board, in marker lengths; ``lighting``: amplitude
    of the slow change of light (0 = constant light); ``supersample``: each pixel is the mean of
    ``supersample`` x ``supersample`` rendered samples (1: one bilinear sample of the texture's mip level)."""

    dictionary: str = "DICT_4X4_50"
    ids: tuple[int, ...] = (0, 1, 2, 3, 4, 5)
    marker_length: float = 0.05
    distance: tuple[float, float] = (3.2, 16.0)
    lighting: float = 0.0
    supersample: int = 1

    def __post_init__(self) -> None:
        super().__post_init__()
        self.check_float("marker_length", 0.0, 10.0, low_open=True)
        self.check_float("lighting", 0.0, 0.9)
        self.check_int("supersample", 1, 8)
        near, far = self.distance if isinstance(self.distance, list | tuple) and len(self.distance) == 2 else (0, 0)
        if not all(isinstance(d, numbers.Real) and not isinstance(d, bool) and math.isfinite(d) for d in (near, far)) \
                or not 1.0 <= near <= far <= 1000.0:
            raise ValueError(f"option distance={self.distance!r}: must be (near, far) marker lengths, "
                             "1 <= near <= far <= 1000")
        object.__setattr__(self, "distance", (float(near), float(far)))
        self.check_choice("dictionary", DICTIONARY_NAMES)
        size = len(aruco_dictionary(self.dictionary).bytesList)
        ids = tuple(self.ids) if isinstance(self.ids, list | tuple) else ()
        integers = all(isinstance(i, numbers.Integral) and not isinstance(i, bool) and 0 <= i < size for i in ids)
        if not (integers and 0 < len(ids) <= 64 and len(set(ids)) == len(ids)):
            raise ValueError(f"option ids={self.ids!r}: must be 1 to 64 distinct integers in [0, {size - 1}]")
        object.__setattr__(self, "ids", tuple(int(i) for i in ids))


class MarkersScene(SyntheticScene):
    """Attributes: ``dictionary`` (cv2.aruco.Dictionary), ``marker_length`` (m), ``board``
    (PlaneTexture of the whole board), ``marker_poses`` (id -> (4, 4) T_board_marker) and
    ``marker_corners`` (id -> (4, 3) corners in the board frame, ArUco order TL, TR, BR, BL)."""

    name = "markers"
    Options = MarkersOptions
    options: MarkersOptions

    def fixtures(self) -> Fixtures:
        """The board as a marker map (``board``: the board frame, ``marker_poses``) and the side and dictionary of
        the markers it draws (every marker has the same side)."""
        o = self.options
        return Fixtures(self.name, self.cameras,
                        marker_map=MarkerLayout("board", o.dictionary, self.marker_length, dict(self.marker_poses)),
                        settings={"marker_length": self.marker_length, "dictionary": o.dictionary})

    def __init__(self, options: MarkersOptions | None = None):
        super().__init__(options)
        o = self.options
        self.dictionary = aruco_dictionary(o.dictionary)
        self.marker_length = o.marker_length
        self.board, self.marker_poses = self.make_board(o.ids)
        corners = rectangle_corners(o.marker_length, o.marker_length)
        self.marker_corners = {i: transform_points(T, corners) for i, T in self.marker_poses.items()}
        L = o.marker_length
        self.path = plane_viewing_path(scene_rng(o.seed, PATH_PURPOSE), near=o.distance[0] * L,
                                       far=o.distance[1] * L, lateral=(4.0 * L, 3.0 * L), wander=(2.5 * L, 1.8 * L),
                                       roll=0.4)
        self.light = Lighting(scene_rng(o.seed, LIGHT_PURPOSE), o.lighting)
        K = intrinsics(o.width, o.height, HFOV_DEG)
        self.cameras = (CameraModel("cam0", o.width, o.height, K, np.zeros(5), np.eye(4)),)

    def make_board(self, ids: tuple[int, ...]) -> tuple[PlaneTexture, dict[int, np.ndarray]]:
        """The board texture and each marker's pose in the board frame."""
        marker_texels = (self.dictionary.markerSize + 2) * CELL_TEXELS
        pitch = 2 * marker_texels
        columns = min(len(ids), math.ceil(math.sqrt(1.5 * len(ids))))
        rows = math.ceil(len(ids) / columns)
        image = np.full((rows * pitch, columns * pitch), BOARD_WHITE, np.uint8)
        metres_per_texel = self.marker_length / marker_texels
        poses = {}
        for n, marker_id in enumerate(ids):
            row, column = divmod(n, columns)
            top, left = row * pitch + marker_texels // 2, column * pitch + marker_texels // 2
            image[top:top + marker_texels, left:left + marker_texels] = cv2.aruco.generateImageMarker(
                self.dictionary, marker_id, marker_texels, borderBits=1)
            centre = np.array([(column + 0.5 - columns / 2), (rows / 2 - row - 0.5), 0.0]) * pitch * metres_per_texel
            poses[marker_id] = make_transform(np.eye(3), centre)
        printed = cv2.convertScaleAbs(image, alpha=1.0 / (1.0 + 2.0 * self.options.lighting))  # see the module doc
        return PlaneTexture(printed, columns * pitch * metres_per_texel, rows * pitch * metres_per_texel), poses

    def camera_pose(self, index: int) -> np.ndarray:
        """(4, 4) ``T_board_cam0`` of frame ``index``."""
        return self.path.pose(self.time_s(index))

    def draw(self, index: int) -> tuple[dict[str, np.ndarray], dict[str, Truth]]:
        camera = self.cameras[0]
        T_cam_board = invert(self.camera_pose(index))
        s = self.options.supersample
        if s == 1:
            image = self.board.warp(camera.K, T_cam_board, (camera.width, camera.height), border_value=OUTSIDE_GREY)
        else:  # fine pixel (i, j) of image pixel (u, v) is centred at (s u + i, s v + j), i, j in 0 .. s - 1
            fine = np.diag([s, s, 1.0]) @ camera.K
            fine[:2, 2] += (s - 1) / 2
            image = self.board.warp(fine, T_cam_board, (camera.width * s, camera.height * s),
                                    border_value=OUTSIDE_GREY)
            image = cv2.resize(image, (camera.width, camera.height), interpolation=cv2.INTER_AREA)
        image = self.light.apply(image, self.time_s(index))
        truth = []
        for marker_id, T_board_marker in self.marker_poses.items():
            corners_cam = transform_points(T_cam_board, self.marker_corners[marker_id])
            if np.all(corners_cam[:, 2] > 0) and inside_image(project_points(corners_cam, camera.K), camera):
                truth.append(("cam0", f"marker/{marker_id}", T_cam_board @ T_board_marker))
        return {"cam0": image}, {"cam0": truth}


def inside_image(pixels: np.ndarray, camera: CameraModel) -> bool:
    """Whether every (N, 2) pixel lies within the image (pixel centres 0..W-1, 0..H-1)."""
    return bool(np.all((pixels >= 0) & (pixels <= (camera.width - 1, camera.height - 1))))
