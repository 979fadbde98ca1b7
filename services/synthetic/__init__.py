"""Synthetic scenes with ground truth: ``make_scene(name, **options)``, and their fixtures.

Scenes are pure algorithms (numpy, OpenCV, ``services.geometry``, the marker dictionaries of
``services.detection.markers``): ``scene.render(index)`` returns a ``SceneFrame`` with every
camera's image and ground-truth transforms, and ``scene.fixtures()`` (``scene_fixtures(name,
**options)``) what a tracker must be told to track the scene (its rig, rigid bodies, image target,
marker map and settings, as data: ``fixtures.py``). See ``base.py`` for the interface and the
options every scene takes, and each scene's module for its world, frames and own options. No
tracker imports this package: the job assembly turns a scene's fixtures into the files trackers read.
"""

from __future__ import annotations

from services.synthetic.base import CameraModel, Scene, SceneFrame, SceneOptions, SyntheticScene
from services.synthetic.fixtures import Fixtures, ImageTarget, MarkerLayout
from services.synthetic.ir_rig import IrRigScene
from services.synthetic.markers import MarkersScene
from services.synthetic.pattern import PatternScene
from services.synthetic.planar_target import PlanarTargetScene
from services.synthetic.room import RoomScene

SCENES: dict[str, type[SyntheticScene]] = {
    cls.name: cls for cls in (MarkersScene, IrRigScene, PlanarTargetScene, RoomScene, PatternScene)
}
"""Scene name -> scene class; each class's ``Options`` lists its options."""

__all__ = ["SCENES", "CameraModel", "Fixtures", "ImageTarget", "MarkerLayout", "Scene", "SceneFrame", "SceneOptions",
           "make_scene", "scene_fixtures", "scene_options"]


def make_scene(name: str, **options) -> Scene:
    """The scene ``name`` built with ``options``; ValueError names an unknown scene or option."""
    if name not in SCENES:
        raise ValueError(f"unknown scene {name!r}; valid scenes: {', '.join(sorted(SCENES))}")
    cls = SCENES[name]
    return cls(cls.Options.parse(name, options))


def scene_options(name: str, options: dict[str, object]) -> dict[str, object]:
    """``options`` of scene ``name`` converted to their declared types (text is parsed by the option's type);
    ValueError names an unknown scene or option, or a value that does not fit."""
    if name not in SCENES:
        raise ValueError(f"unknown scene {name!r}; valid scenes: {', '.join(sorted(SCENES))}")
    cls = SCENES[name].Options
    parsed = cls.parse(name, {key: cls.from_text(key, value) if isinstance(value, str) else value
                              for key, value in options.items()})
    return {key: getattr(parsed, key) for key in options}


def scene_fixtures(name: str, **options) -> Fixtures:
    """The fixtures of scene ``name`` built with ``options`` (``fixtures.py``); ValueError as ``make_scene``."""
    return make_scene(name, **options).fixtures()
