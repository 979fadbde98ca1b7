"""Synthetic scenes with ground truth: ``make_scene(name, **options)``.

Scenes are pure algorithms (numpy, OpenCV, ``services.geometry``): ``scene.render(index)``
returns a ``SceneFrame`` with every camera's image and ground-truth transforms. See
``base.py`` for the interface and the options every scene takes, and each scene's module
for its world, frames and own options.
"""

from __future__ import annotations

from services.capture.scenes.base import CameraModel, Scene, SceneFrame, SceneOptions, SyntheticScene
from services.capture.scenes.ir_rig import IrRigScene
from services.capture.scenes.markers import MarkersScene
from services.capture.scenes.pattern import PatternScene
from services.capture.scenes.planar_target import PlanarTargetScene
from services.capture.scenes.room import RoomScene

SCENES: dict[str, type[SyntheticScene]] = {
    cls.name: cls for cls in (MarkersScene, IrRigScene, PlanarTargetScene, RoomScene, PatternScene)
}
"""Scene name -> scene class; each class's ``Options`` lists its options."""

__all__ = ["SCENES", "CameraModel", "Scene", "SceneFrame", "SceneOptions", "make_scene", "scene_options"]


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
