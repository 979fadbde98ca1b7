"""A synthetic scene's own image target: the URI the scene settles, and the target built from it."""

from __future__ import annotations

import numpy as np
import pytest

from services.capture.scenes import make_scene
from services.estimation.targets.scene import is_scene_target, scene_target, scene_target_name


def test_the_scene_settles_its_own_target_and_names_the_options_that_shape_it():
    assert make_scene("planar_target").known_settings() == {"target": ("synthetic:planar_target",)}
    uri = make_scene("planar_target", seed=3, texture_px=256, noise_std=2.0).known_settings()["target"][0]
    assert uri == "synthetic:planar_target?seed=3&texture_px=256"


def test_the_target_is_the_scenes_texture_at_its_width():
    uri = "synthetic:planar_target?texture_px=256&target_width=0.5"
    scene = make_scene("planar_target", texture_px=256, target_width=0.5)
    target = scene_target(uri)
    assert is_scene_target(uri) and not is_scene_target("poster")
    assert target.name == scene_target_name(uri) == "planar_target"
    assert np.array_equal(target.image, scene.texture) and target.width_m == 0.5


@pytest.mark.parametrize(("uri", "message"), [
    ("synthetic:nosuch", "unknown scene 'nosuch'"),
    ("synthetic:planar_target?texture_px", "write scene options as name=value"),
    ("synthetic:planar_target?colour=red", "unknown option"),
    ("synthetic:markers", "renders no image target"),
])
def test_a_uri_that_gives_no_target_is_refused_in_one_line(uri, message):
    with pytest.raises(ValueError, match=message) as refused:
        scene_target(uri)
    assert "\n" not in str(refused.value) and uri in str(refused.value)
