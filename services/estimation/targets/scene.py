"""Image targets that synthetic scenes render, built in-process from the scene's own texture.

A scene that shows a printed image (``planar_target``) names its target by a URI:
``synthetic:<scene>`` with, after ``?``, ``name=value`` pairs joined by ``&`` for the scene options
that shape the image (``synthetic:planar_target?seed=3&texture_px=512``; values as text, converted by
the options' types). The scene settles this URI as a tracker's ``target`` when it is the source
(``PlanarTargetScene.known_settings``), so ``artrack run features --source synthetic:planar_target``
tracks the scene's target with no library at all, and a recording of such a run can be tracked again
with ``--target synthetic:planar_target``.

The target is the scene's texture ((h, w) uint8, its ``texture`` attribute), as wide as the scene's
``size_m[0]`` metres, built by ``build_target`` with the default detector settings and named after the
scene (``planar_target``). Its frame is the scene's target frame, so its poses score against the
scene's ground truth as they are.
"""

from __future__ import annotations

import numpy as np

from services.capture.scenes import make_scene, scene_options
from services.estimation.targets.target import Target, build_target

__all__ = ["SCENE_PREFIX", "is_scene_target", "scene_target", "scene_target_name"]

SCENE_PREFIX = "synthetic:"


def is_scene_target(name: str) -> bool:
    """Whether ``name`` is a scene's target URI rather than a library name."""
    return name.startswith(SCENE_PREFIX)


def _parse(uri: str) -> tuple[str, dict[str, object]]:
    """``(scene, options)`` of a scene target URI, options converted by their types; ValueError naming the fault."""
    scene, _, query = uri.removeprefix(SCENE_PREFIX).partition("?")
    texts: dict[str, object] = {}
    for pair in filter(None, query.split("&")):
        name, sep, value = pair.partition("=")
        if not sep or not name:
            raise ValueError(f"target {uri!r}: write scene options as name=value, got {pair!r}")
        texts[name] = value
    try:
        return scene, scene_options(scene, texts)
    except ValueError as exc:
        raise ValueError(f"target {uri!r}: {exc}") from exc


def scene_target_name(uri: str) -> str:
    """The name the target of ``uri`` goes by (its scene's); ValueError for a URI that names no known scene or
    options it does not take."""
    return _parse(uri)[0]


def scene_target(uri: str) -> Target:
    """The target of the scene that ``uri`` names, built from its texture; ValueError when the URI is not valid
    or the scene renders no image target."""
    scene_name, options = _parse(uri)
    scene = make_scene(scene_name, **options)
    texture = getattr(scene, "texture", None)
    size_m = getattr(scene, "size_m", None)
    if not isinstance(texture, np.ndarray) or size_m is None:
        raise ValueError(f"target {uri!r}: scene {scene_name!r} renders no image target (planar_target does)")
    return build_target(scene_name, texture, float(size_m[0]))
