"""A scene's fixtures: what a tracker must be told to track it, as plain data.

``scene.fixtures()`` (or ``scene_fixtures(name, **options)``) gives a ``Fixtures``:

* ``rig``: the scene's cameras (``CameraModel``: intrinsics, distortion, ``T_rig_camera``), every scene;
* ``bodies``: rigid bodies, name -> (N, 3) float64 sphere centres in the body frame, metres (``ir_rig``);
* ``target``: the printed image target, an ``ImageTarget`` (``planar_target``);
* ``marker_map``: markers rigidly placed in one frame, a ``MarkerLayout`` (``markers``' board);
* ``settings``: tracker parameters the scene settles by what it renders, by field name (``markers``,
  ``room`` with its marker: ``marker_length`` and ``dictionary``).

What a scene does not have is empty (no bodies, no settings) or None (no target, no marker map).
The files trackers read are written from this data by the rooms that own their formats (a bodies
file, a target library entry, a marker map file, a rig file): ``services.launcher.fixtures``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from services.geometry.camera import CameraModel

__all__ = ["Fixtures", "ImageTarget", "MarkerLayout"]


@dataclass(frozen=True)
class ImageTarget:
    """A printed image: ``image`` (H, W) uint8 grey, ``width_m`` metres wide (``width_m * H / W`` high),
    named ``name``. Its frame: origin at the image's centre, x right, y up, z out of the image."""

    name: str
    image: np.ndarray
    width_m: float


@dataclass(frozen=True)
class MarkerLayout:
    """Markers of one ``dictionary`` (a cv2.aruco predefined name), all of side ``length`` metres (the black
    square), placed in one frame named ``name``: ``poses`` id -> (4, 4) ``T_map_marker`` (ArUco marker frames:
    origin at the marker's centre, x right, y up, z out of the marker)."""

    name: str
    dictionary: str
    length: float
    poses: dict[int, np.ndarray]


@dataclass(frozen=True)
class Fixtures:
    """The fixtures of scene ``scene`` (see the module docstring)."""

    scene: str
    rig: tuple[CameraModel, ...]
    bodies: dict[str, np.ndarray] = field(default_factory=dict)
    target: ImageTarget | None = None
    marker_map: MarkerLayout | None = None
    settings: dict[str, Any] = field(default_factory=dict)
