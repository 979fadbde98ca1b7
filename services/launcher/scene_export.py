"""A synthetic scene written to files, so a tracker can be run and scored on files alone.

Layout of the folder (``export_scene``)::

    DIR/cam0/0.000000000.png        one folder per camera; each image named by its time in seconds,
    DIR/cam0/0.033333333.png        to the nanosecond (the images source reads the names exactly)
    DIR/cam1/...
    DIR/cam0.yaml, DIR/cam1.yaml    each camera's calibration (camera_info YAML, for --calib)
    DIR/rig.yaml                    every camera's intrinsics and T_rig_camera (two or more cameras)
    DIR/bodies.yaml                 the scene's rigid bodies (scenes that have them: ir_rig)
    DIR/targets/<name>.npz, .png    the scene's image target, a target library (planar_target)
    DIR/marker_map.yaml             the scene's markers as a marker map (markers: its board)
    DIR/truth/<name>.tum            ground truth as TUM, one file per child frame
    DIR/scene.yaml                  the scene, its options and the frame count (to make it again)

The rig, bodies, target and marker map are the scene's fixtures (``services.synthetic.fixtures``),
written by ``services.launcher.fixtures.write_fixtures``.

Truth files: a transform whose parent frame is the world (``ir_rig``'s ``T_world_body``, ``room``'s
``T_world_cam0``) goes to ``truth/<name>.tum``, ``<name>`` the last part of its child frame
(``body/tool`` -> ``truth/tool.tum``); one whose parent is a camera (``markers``'
``T_cam0_marker``) to ``truth/<camera>/<name>.tum``. A line per frame where the transform is known,
stamped with the frame's time, the same stamp its images carry.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import yaml

from services.calibration.camera_info import write_camera_info
from services.convert import transform_from_matrix
from services.launcher.fixtures import FixtureFiles, write_fixtures
from services.recorder.export import tum_line
from services.synthetic import make_scene

__all__ = ["SceneExport", "SceneExportError", "export_scene", "image_name", "truth_path"]

NS_PER_S = 1_000_000_000


class SceneExportError(ValueError):
    """A scene, option or output folder that cannot be exported to; one line saying why."""


@dataclass
class SceneExport:
    """What ``export_scene`` wrote: ``images`` per camera, ``truth`` rows per file, and ``fixtures``, the rig,
    bodies, target library and marker map (None where the scene has none; ``fixtures.notes`` says why one it
    has was not written)."""

    folder: Path
    cameras: tuple[str, ...]
    frames: int
    fixtures: FixtureFiles
    images: int = 0
    truth: dict[Path, int] = field(default_factory=dict)


def image_name(time_ns: int, suffix: str = ".png") -> str:
    """A frame's file name: its time in decimal seconds with nine digits (``0.033333333.png``), read
    back exactly as int nanoseconds by the images source (``services.calibration.image_folder.seconds_to_ns``)."""
    return f"{time_ns // NS_PER_S}.{time_ns % NS_PER_S:09d}{suffix}"


def truth_path(folder: Path, parent: str, child: str, cameras: tuple[str, ...]) -> Path:
    """Where the truth of ``T_parent_child`` goes (see the module's docstring)."""
    name = child.rsplit("/", 1)[-1]
    return folder / "truth" / parent / f"{name}.tum" if parent in cameras else folder / "truth" / f"{name}.tum"


def export_scene(scene_name: str, out: Path, frames: int, options: Mapping[str, object] | None = None) -> SceneExport:
    """Write ``frames`` frames of scene ``scene_name`` (built with ``options``, typed values) into ``out``.

    ``out`` must be absent or an empty folder. Raises SceneExportError for an unknown scene or option,
    a frame count below 1, or an output folder that is not empty.
    """
    if frames < 1:
        raise SceneExportError(f"--frames must be 1 or more, got {frames}")
    try:
        scene = make_scene(scene_name, **dict(options or {}))
    except ValueError as exc:
        raise SceneExportError(str(exc)) from exc
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise SceneExportError(f"{out}: exists and is not an empty folder (the export would mix with it)")
    cameras = tuple(camera.name for camera in scene.cameras)
    done = SceneExport(out, cameras, frames, write_fixtures(out, scene.fixtures()))
    for camera in scene.cameras:
        (out / camera.name).mkdir(parents=True, exist_ok=True)
        write_camera_info(out / f"{camera.name}.yaml", camera)
    (out / "scene.yaml").write_text(yaml.safe_dump(
        {"scene": scene_name, "options": {k: _plain(v) for k, v in (options or {}).items()}, "frames": frames},
        sort_keys=False))
    lines: dict[Path, list[str]] = {}
    for index in range(frames):
        frame = scene.render(index)
        time_ns = round(frame.time_s * NS_PER_S)
        for name, image in frame.images.items():
            cv2.imwrite(str(out / name / image_name(time_ns)), image)
            done.images += 1
        written: set[Path] = set()
        for camera_truth in frame.truth.values():
            for parent, child, T in camera_truth:
                path = truth_path(out, parent, child, cameras)
                if path not in written:
                    written.add(path)
                    lines.setdefault(path, []).append(tum_line(time_ns, transform_from_matrix(T)))
    for path, rows in lines.items():
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text("# stamp tx ty tz qx qy qz qw\n" + "".join(f"{row}\n" for row in rows))
        done.truth[path] = len(rows)
    return done


def _plain(value: object) -> object:
    """An option value as YAML writes it plainly (tuples as lists, numpy scalars as numbers)."""
    if isinstance(value, tuple | list):
        return [_plain(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    return value
