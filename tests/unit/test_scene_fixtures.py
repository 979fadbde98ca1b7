"""A scene's fixtures as data (``services.synthetic``) and as the files a job's trackers read
(``services.launcher.fixtures``): what a synthetic source settles of a tracker's options, and a target
named ``synthetic:SCENE``."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from services.bus.session import BusConfig
from services.estimation.bodies.file import load_bodies
from services.estimation.targets.library import TargetLibrary
from services.launcher.fixtures import fixture_folder, scene_settings, scene_target_library
from services.synthetic import SCENES, make_scene, scene_fixtures
from services.synthetic.ir_rig import LAYOUTS

SMALL = {"width": 160, "height": 120}


@pytest.fixture(autouse=True)
def cache(tmp_path, monkeypatch):
    """The job folders of this test's scenes, under a cache of its own."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    return tmp_path / "cache"


@pytest.mark.parametrize("name", sorted(SCENES))
def test_every_scene_gives_its_rig_and_only_the_fixtures_it_renders(name):
    scene = make_scene(name, **SMALL)
    fixtures = scene.fixtures()
    assert fixtures.scene == name and fixtures.rig == scene.cameras
    assert bool(fixtures.bodies) == (name == "ir_rig")
    assert (fixtures.target is not None) == (name == "planar_target")
    assert (fixtures.marker_map is not None) == (name == "markers")
    assert bool(fixtures.settings) == (name == "markers")


def test_the_ir_rig_gives_the_bodies_it_shows_and_the_target_scene_its_texture():
    bodies = scene_fixtures("ir_rig", body_count=2).bodies
    assert list(bodies) == list(LAYOUTS)[:2] and all(np.array_equal(bodies[n], LAYOUTS[n]) for n in bodies)
    scene = make_scene("planar_target", texture_px=256, target_width=0.5)
    target = scene.fixtures().target
    assert target is not None and target.name == "planar_target" and target.width_m == 0.5
    assert np.array_equal(target.image, scene.texture)


def test_a_job_folder_is_one_per_scene_and_options():
    assert fixture_folder("ir_rig", {"seed": 1}) == fixture_folder("ir_rig", {"seed": 1})
    assert fixture_folder("ir_rig", {"seed": 1}) != fixture_folder("ir_rig", {"seed": 2})
    assert fixture_folder("ir_rig", {}).name.startswith("ir_rig-")


def test_a_markers_source_settles_its_marker_side_and_dictionary_and_other_sources_nothing():
    settled = scene_settings(("synthetic:markers",), {"marker_length": 0.1})
    assert [(s.uri, s.fields, s.values()) for s in settled] == [
        ("synthetic:markers", ("marker_length",), {"marker_length": 0.1}),
        ("synthetic:markers", ("dictionary",), {"dictionary": "DICT_4X4_50"})]
    assert scene_settings(("synthetic:pattern", "camera:0", "images:/tmp"), {}) == []


def test_an_ir_rig_source_settles_its_bodies_file_in_the_job_folder(cache):
    (settled,) = scene_settings(("synthetic:ir_rig",), {"body_count": 2})
    assert settled.fields == ("bodies",)
    path = settled.values()["bodies"]
    assert path == str(fixture_folder("ir_rig", {"body_count": 2}) / "bodies.yaml") and path.startswith(str(cache))
    assert list(load_bodies(path)) == list(LAYOUTS)[:2]
    assert settled.values() == {"bodies": path}  # written again, in place
    assert [p.name for p in fixture_folder("ir_rig", {"body_count": 2}).iterdir()] == ["bodies.yaml"]


def test_a_wand_settles_no_bodies_file():
    (settled,) = scene_settings(("synthetic:ir_rig",), {"motion": "wand"})
    assert settled.values() == {}


def test_a_target_source_settles_its_target_in_a_library_of_its_own():
    (settled,) = scene_settings(("synthetic:planar_target",), {"texture_px": 256})
    assert settled.fields == ("target", "targets")
    values = settled.values()
    assert values["target"] == ("planar_target",)
    target = TargetLibrary(values["targets"]).load("planar_target")
    assert np.array_equal(target.image, make_scene("planar_target", texture_px=256).texture)


def test_a_target_named_by_its_scene_is_that_scenes_own():
    assert scene_target_library(["poster"], library_given=False) is None
    values = scene_target_library(["synthetic:planar_target?texture_px=256&target_width=0.5"], library_given=False)
    assert values is not None and values["target"] == ("planar_target",)
    target = TargetLibrary(values["targets"]).load("planar_target")
    assert target.width_m == 0.5 and target.image.shape[1] == 256
    assert values["targets"] == str(fixture_folder("planar_target", {"texture_px": 256, "target_width": 0.5})
                                    / "targets")


@pytest.mark.parametrize(("names", "message"), [
    (["synthetic:nosuch"], "unknown scene 'nosuch'"),
    (["synthetic:planar_target?texture_px"], "write scene options as name=value"),
    (["synthetic:planar_target?colour=red"], "unknown option"),
    (["synthetic:markers"], "renders no image target"),
    (["poster", "synthetic:planar_target"], "a scene's target is tracked alone"),
])
def test_a_scene_target_that_cannot_be_made_is_refused_in_one_line(names, message):
    with pytest.raises(ValueError, match=message) as refused:
        scene_target_library(names, library_given=False)
    assert "\n" not in str(refused.value) and names[-1] in str(refused.value)


def test_a_scene_target_beside_a_library_is_refused():
    with pytest.raises(ValueError, match="a scene's target is tracked alone"):
        scene_target_library(["synthetic:planar_target"], library_given=True)



def assembled(tracker: str, given: dict[str, str], scene: dict[str, str] | None = None) -> dict[str, dict]:
    """The nodes' parameters of ``artrack run TRACKER`` with the flags ``given`` (option -> text) and
    ``--scene-option``s ``scene``."""
    from services.cli.run import SOURCE_SKIP
    from services.launcher.assembly import JobRequest, assemble
    from services.launcher.flags import flags_for
    from services.launcher.kinds import kind
    from services.launcher.tracker import Tracker

    source = flags_for(kind("capture").params, SOURCE_SKIP)
    own = Tracker.load(tracker).flags({flag.field: flag for flag in source})
    by_option = {flag.option: flag for flag in [*source, *own]}
    request = JobRequest(tracker=tracker, bus=lambda defaults: BusConfig(**defaults), flags=own, source_flags=source,
                         source={by_option[o].key: [v] if o == "--source" else v for o, v in given.items()
                                 if by_option[o] in source},
                         options={by_option[o].key: v for o, v in given.items() if by_option[o] in own},
                         scene=scene or {})
    return {name: node.params for name, node in assemble(request)[1].nodes.items()}


def test_the_job_assembly_gives_the_trackers_what_their_scene_settles_unless_given(caplog, tmp_path):
    caplog.set_level("INFO", "artrack")
    bodies = assembled("stereo", {"--source": "synthetic:ir_rig"})["bodies"]["bodies"]
    assert bodies == str(fixture_folder("ir_rig", {}) / "bodies.yaml")
    assert list(load_bodies(bodies)) == list(LAYOUTS)[:3]
    assert f"using --bodies {bodies}, as synthetic:ir_rig renders it" in caplog.text
    (tmp_path / "mine.yaml").write_text(Path(bodies).read_text())
    given = assembled("stereo", {"--source": "synthetic:ir_rig", "--bodies": str(tmp_path / "mine.yaml")})
    assert given["bodies"]["bodies"] == str(tmp_path / "mine.yaml")
    caplog.clear()
    marker = assembled("marker", {"--source": "synthetic:markers"})["marker-cam0"]
    assert marker["marker_length"] == 0.05 and "dictionary" not in marker  # the default dictionary: nothing to tell
    assert "using --marker-length 0.05" in caplog.text and "--dictionary" not in caplog.text
    other = assembled("marker", {"--source": "synthetic:markers"}, {"dictionary": "DICT_5X5_50"})["marker-cam0"]
    assert other["dictionary"] == "DICT_5X5_50"
    features = assembled("features", {"--source": "synthetic:pattern", "--target": "synthetic:planar_target"})
    assert list(features["features-cam0"]["target"]) == ["planar_target"]
    assert features["features-cam0"]["targets"].endswith("/targets")
