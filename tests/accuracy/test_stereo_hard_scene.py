"""The stereo tracker's defaults on the hard ``ir_rig`` scene (``stereo_losses.HARD``): seeds 0 to 5, 360 frames
each at 120 Hz (the bar's two conditions: seeds 0 to 2).

Three arc cameras at different distances, each with its distortion; the tool (4 spheres) and the head (5),
15 mm spheres; a sphere hidden from one camera now and then, two stray reflections, the bodies turning four
times as far and fast as the default scene's so that spheres merge in some views. Run and scored by
``stereo_losses.analyse`` as ``artrack run stereo`` runs the tracker, the seeds' frames pooled; and the bar of
three cameras 0.3 m apart (``stereo_losses.BASE``), alone and with the bodies spinning, where two spheres merged in
one view are merged in all. Requirements: no ghost; per body the tracked share of the trackable frames and the
median position and rotation errors no worse than the floors below; every frame lost given one cause and one stage.
"""

from __future__ import annotations

from functools import cache

import numpy as np
import pytest

from services.geometry.camera_stack import CameraStack
from tests.accuracy.stereo_losses import FRAMES, Discs, Verdict, analyse, conditions, figures, hard_scene

pytestmark = pytest.mark.slow

SEEDS = range(6)
BAR_SEEDS = range(3)
FLOORS = {"tool": {"tracked_percent": 99.5, "position_mm_median": 0.06, "rotation_deg_median": 0.06},
          "head": {"tracked_percent": 99.5, "position_mm_median": 0.06, "rotation_deg_median": 0.06}}
"""Floors of the hard scene under today's figures (every body tracked in all its 2160 trackable frames, tool 0.041 mm
and 0.043 deg, head 0.037 mm and 0.034 deg), with a margin for a change that moves a few frames."""
BAR_FLOORS = {"tracked_percent": 99.0, "position_mm_median": 0.3, "rotation_deg_median": 0.3}
"""The bar of three cameras 0.3 m apart (``base``, and ``spin alone``: two spheres merged in every view at once):
the requirement itself (tracked in at least 99 % of the trackable frames, medians within 0.3 mm and 0.3 deg); today
every body is tracked in all 1080 trackable frames of ``BAR_SEEDS`` in either, at 0.078 to 0.090 mm and 0.084 to
0.098 deg (in all 2160 of seeds 0 to 5 too, at 0.075 to 0.088 mm and 0.079 to 0.102 deg)."""


@cache
def verdicts(condition: str = "all (hard)", seeds: range = SEEDS) -> list[Verdict]:
    changes = dict(conditions("all", {}))[condition]
    return [v for seed in seeds for v in analyse(hard_scene(**{**changes, "seed": seed}), FRAMES)]


def unexplained(found: list[Verdict]) -> list[Verdict]:
    """The frames of ``found`` lost without one cause and one stage named."""
    return [v for v in found if v.outcome == "lost" and not (v.cause and v.stage)]


def test_the_hard_conditions_occur_in_the_frames():
    scene = hard_scene()
    stack = CameraStack.of(list(scene.cameras))
    merged = strays = hidden = 0
    for index in range(0, FRAMES, 2):
        discs = Discs.of(scene, stack, index)
        spheres = discs.owner != ""
        gap = np.linalg.norm(discs.pixels[spheres][:, None] - discs.pixels[spheres][None], axis=3)
        touching = gap < discs.radii[spheres][:, None] + discs.radii[spheres][None]
        touching &= discs.lit[spheres][:, None] & discs.lit[spheres][None]
        touching[np.arange(len(gap)), np.arange(len(gap))] = False
        merged += bool(np.any(touching))
        strays += bool(np.any(~spheres))
        hidden += bool(scene.occlusions(index))
    assert merged >= 5 and strays >= 60 and hidden >= 20, (merged, strays, hidden)


def test_the_defaults_track_the_hard_scene_without_a_ghost_above_the_floors():
    found = figures(verdicts())
    print(found)
    assert not unexplained(verdicts())
    for name, floors in FLOORS.items():
        body = found[name]
        assert body["ghosts"] == 0, (name, body)
        assert body["trackable"] >= 0.9 * FRAMES * len(SEEDS), (name, body)
        assert body["tracked_percent"] >= floors["tracked_percent"], (name, body)
        assert body["position_mm_median"] <= floors["position_mm_median"], (name, body)
        assert body["rotation_deg_median"] <= floors["rotation_deg_median"], (name, body)


UNSEEN_SEEDS = range(6, 12)
"""Seeds of the hard scene the defaults were not tuned on. On seed 7 a sphere's point 8 mm off (one view biased by a
blob it merged with) once gave the tool six ghost poses in a row, 2.5-3 mm and 5-6.5 deg off: the fit let a good
sphere go instead of that point (its largest residual lay elsewhere). Today every body is tracked in all 2160
trackable frames of these seeds."""


def test_seeds_the_defaults_were_not_tuned_on_are_tracked_without_a_ghost_above_the_floors():
    unseen = [v for seed in UNSEEN_SEEDS for v in analyse(hard_scene(seed=seed), FRAMES)]
    found = figures(unseen)
    print(found)
    assert not unexplained(unseen)
    for name, floors in FLOORS.items():
        body = found[name]
        assert body["ghosts"] == 0, (name, body)
        assert body["tracked_percent"] >= floors["tracked_percent"], (name, body)
        assert body["position_mm_median"] <= floors["position_mm_median"], (name, body)
        assert body["rotation_deg_median"] <= floors["rotation_deg_median"], (name, body)


@pytest.mark.parametrize("condition", ["base", "spin alone"])
def test_the_defaults_track_the_bar_where_spheres_merge_in_every_view(condition):
    found = figures(verdicts(condition, BAR_SEEDS))
    print(condition, found)
    assert not unexplained(verdicts(condition, BAR_SEEDS))
    for name, body in found.items():
        assert body["ghosts"] == 0, (name, body)
        assert body["trackable"] >= 0.9 * FRAMES * len(BAR_SEEDS), (name, body)
        assert body["tracked_percent"] >= BAR_FLOORS["tracked_percent"], (name, body)
        assert body["position_mm_median"] <= BAR_FLOORS["position_mm_median"], (name, body)
        assert body["rotation_deg_median"] <= BAR_FLOORS["rotation_deg_median"], (name, body)
