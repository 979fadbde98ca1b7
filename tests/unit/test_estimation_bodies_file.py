"""Bodies files: round trip, the scene's layouts as a file, refusals naming the file, warnings."""

from pathlib import Path

import numpy as np
import pytest
import yaml

from services.estimation.bodies.file import BodiesFileError, check_bodies, load_bodies, save_bodies
from services.geometry.rotation import matrix_from_rotvec
from services.synthetic.ir_rig import LAYOUTS

LAYOUTS_FILE = Path(__file__).parents[2] / "pipelines" / "ir_rig_bodies.yaml"
EQUILATERAL = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.05, 0.05 * np.sqrt(3), 0.0]])


def test_layouts_file_holds_the_ir_rig_scene_bodies():
    bodies = load_bodies(LAYOUTS_FILE)
    assert list(bodies) == list(LAYOUTS)
    for name, spheres in LAYOUTS.items():
        assert np.array_equal(bodies[name], spheres)


def test_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    bodies = {"a": rng.uniform(-0.1, 0.1, (4, 3)), "b.2": rng.uniform(-0.1, 0.1, (5, 3))}
    save_bodies(tmp_path / "b.yaml", bodies)
    loaded = load_bodies(tmp_path / "b.yaml")
    assert list(loaded) == ["a", "b.2"]
    assert all(np.array_equal(loaded[k], bodies[k]) for k in bodies)


def write(tmp_path: Path, document: object) -> Path:
    path = tmp_path / "bodies.yaml"
    path.write_text(yaml.safe_dump(document))
    return path


@pytest.mark.parametrize(("document", "message"), [
    ({"bodies": [{"name": "a", "spheres": [[0, 0, 0], [0.1, 0, 0]]}]}, "body 'a': has 2 sphere"),
    ({"bodies": [{"name": "a", "spheres": EQUILATERAL.tolist()},
                 {"name": "a", "spheres": EQUILATERAL.tolist()}]}, "bodies\\[1\\].name: body 'a' appears twice"),
    ({"bodies": [{"name": "a", "spheres": [[0, 0, 0], [0.1, 0, 0], [0.1, 0.005, 0]]}]},
     "spheres 1 and 2 are 5.0 mm apart, closer than the minimum 10.0 mm"),
    ({"bodies": [{"name": "a", "spheres": [[0, 0, 0], [0.1, 0, 0], [0.2, 0, 0]]}]}, "one line"),
    ({"bodies": [{"name": "a/b", "spheres": EQUILATERAL.tolist()}]}, "name: must be a word"),
    ({"bodies": [{"name": "a", "spheres": [[0, 0, "x"], [0.1, 0, 0], [0.2, 0, 0]]}]}, "finite numbers"),
    ({"bodies": [{"name": "a", "spheres": [[0, 0], [0.1, 0], [0.2, 0]]}]}, r"list of \[x, y, z\]"),
    ({"bodies": [{"name": "a"}]}, "exactly name and spheres"),
    ({"bodies": []}, "non-empty list"),
    ([1, 2], "single field bodies"),
])
def test_bad_files_are_refused_in_one_line_naming_the_file(tmp_path, document, message):
    path = write(tmp_path, document)
    with pytest.raises(BodiesFileError, match=message) as error:
        load_bodies(path)
    text = str(error.value)
    assert text.startswith(f"{path}: ") and "\n" not in text


def test_unreadable_and_invalid_yaml_are_refused(tmp_path):
    with pytest.raises(BodiesFileError, match="missing.yaml: cannot read the file"):
        load_bodies(tmp_path / "missing.yaml")
    path = tmp_path / "broken.yaml"
    path.write_text("bodies: [\n  {name: a\n")
    with pytest.raises(BodiesFileError, match="broken.yaml: not valid YAML") as error:
        load_bodies(path)
    assert "\n" not in str(error.value)


def test_minimum_separation_is_a_parameter(tmp_path):
    path = write(tmp_path, {"bodies": [{"name": "a", "spheres": EQUILATERAL.tolist()}]})
    assert "a" in load_bodies(path, min_separation=0.05)
    with pytest.raises(BodiesFileError, match="closer than the minimum 120.0 mm"):
        load_bodies(path, min_separation=0.12)


def test_scene_layouts_draw_no_warning():
    assert check_bodies(LAYOUTS) == []


@pytest.mark.parametrize("spheres", [
    EQUILATERAL,
    np.array([[0.0, 0.0, 0.0], [0.12, 0.0, 0.0], [0.06, 0.09, 0.0]]),
])
def test_symmetric_triangles_are_warned(spheres):
    warnings = check_bodies({"tri": spheres})
    assert len(warnings) == 1 and "'tri' is symmetric (all spheres seen)" in warnings[0]


def test_a_body_symmetric_only_with_one_sphere_hidden_is_warned():
    # The first three spheres make an isosceles triangle; the fourth tells its two halves apart
    spheres = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.05, 0.15, 0.0], [0.03, -0.02, 0.05]])
    warnings = check_bodies({"quad": spheres})
    assert warnings == ["body 'quad' is symmetric (sphere 3 hidden): 2 sphere assignments fit, "
                        "its orientation is ambiguous"]


def test_two_alike_bodies_are_warned_both_ways():
    other = LAYOUTS["tool"] @ matrix_from_rotvec(np.array([0.3, 0.2, -0.5])).T + 0.001
    warnings = check_bodies({"tool": LAYOUTS["tool"], "copy": other})
    assert len(warnings) == 2
    assert "body 'tool' is too like body 'copy'" in warnings[0]
    assert "body 'copy' is too like body 'tool'" in warnings[1]


@pytest.mark.parametrize(("scale", "unit"), [(1000, "millimetres"), (100, "centimetres")])
def test_a_body_wider_than_plausible_is_warned_naming_the_likely_unit(scale, unit):
    spheres = LAYOUTS["tool"]
    across = max(np.linalg.norm(a - b) for a in spheres for b in spheres)
    assert check_bodies({"probe": spheres}) == [] and 0.1 < across < 2
    warnings = check_bodies({"probe": spheres * scale})
    assert len(warnings) == 1 and warnings[0].startswith(f"body 'probe' is {across * scale:.3g} m across (at most "
                                                         "2 m is plausible)"), warnings
    assert f"typed in {unit}? It would be {across:.3g} m across" in warnings[0]


def test_a_body_wider_than_any_unit_explains_is_warned_with_the_unit_of_the_file():
    warnings = check_bodies({"huge": np.array([[0.0, 0.0, 0.0], [5e3, 0.0, 0.0], [0.0, 4e3, 0.0]])})
    assert len(warnings) == 1 and warnings[0].endswith("m across (at most 2 m is plausible): a bodies file is in "
                                                       "metres"), warnings
