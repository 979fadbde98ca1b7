"""Rigid body matching: assignments, hidden spheres, ghosts, the global choice between bodies."""

import numpy as np
import pytest

from services.estimation.bodies.rigid import MatchOptions, body_candidates, match_bodies
from services.geometry.evaluation import pose_error
from services.geometry.rotation import matrix_from_rotvec
from services.geometry.se3 import make_transform, transform_points
from services.synthetic.ir_rig import LAYOUTS

POSES = {name: make_transform(matrix_from_rotvec(np.array([0.3 * k, -0.5, 0.2 + k])),
                               np.array([0.3 * k - 0.5, 0.1, 2.0 + 0.1 * k]))
         for k, name in enumerate(LAYOUTS)}


def scene_points(rng: np.random.Generator, ghosts: int = 0) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Shuffled world points of every body (plus ghosts) and name -> (N,) index of each sphere's point."""
    points = np.concatenate([transform_points(POSES[n], LAYOUTS[n]) for n in LAYOUTS]
                            + [rng.uniform([-0.8, -0.5, 1.6], [0.8, 0.5, 2.8], (ghosts, 3))])
    order = rng.permutation(len(points))
    where = np.argsort(order)
    sizes = np.cumsum([0] + [len(s) for s in LAYOUTS.values()])
    truth = {n: where[sizes[k]:sizes[k + 1]] for k, n in enumerate(LAYOUTS)}
    return points[order], truth


def test_every_body_is_found_with_its_spheres_and_pose():
    rng = np.random.default_rng(0)
    points, truth = scene_points(rng, ghosts=12)
    result = match_bodies(LAYOUTS, points)
    assert set(result.bodies) == set(LAYOUTS)
    for name, match in result.bodies.items():
        assert np.array_equal(match.indices, truth[name])
        rotation, translation = pose_error(match.fit.T_world_body, POSES[name])
        assert rotation < 1e-6 and translation < 1e-9
        assert match.spheres_used == len(LAYOUTS[name]) and match.fit.covariance is None
    used = np.concatenate(list(truth.values()))
    assert np.array_equal(result.unassigned, np.setdiff1d(np.arange(len(points)), used))


def test_one_hidden_sphere_is_tolerated_from_four_spheres_up_but_not_for_three():
    rng = np.random.default_rng(1)
    points, truth = scene_points(rng)
    hidden = [truth["head"][2], truth["wand"][0]]
    result = match_bodies(LAYOUTS, np.delete(points, hidden, axis=0))
    assert set(result.bodies) == {"tool", "head", "glove"}
    head = result.bodies["head"]
    assert head.indices[2] == -1 and head.spheres_used == 4
    assert pose_error(head.fit.T_world_body, POSES["head"])[1] < 1e-9
    strict = match_bodies(LAYOUTS, np.delete(points, hidden, axis=0), options=MatchOptions(allow_missing=False))
    assert set(strict.bodies) == {"tool", "glove"}


@pytest.mark.parametrize("hidden", [2, 3])
def test_three_seen_spheres_find_a_body_of_any_size(hidden):
    rng = np.random.default_rng(2)
    points, truth = scene_points(rng)
    result = match_bodies(LAYOUTS, np.delete(points, truth["glove"][:hidden], axis=0))
    assert set(result.bodies) == set(LAYOUTS)
    glove = result.bodies["glove"]
    assert np.all(glove.indices[:hidden] == -1) and glove.spheres_used == 6 - hidden
    rotation, translation = pose_error(glove.fit.T_world_body, POSES["glove"])
    assert rotation < 1e-6 and translation < 1e-9


def test_a_five_sphere_body_is_found_from_three_beside_the_others_and_ghosts():
    rng = np.random.default_rng(6)
    points, truth = scene_points(rng, ghosts=8)
    result = match_bodies(LAYOUTS, np.delete(points, truth["head"][[0, 3]], axis=0))
    assert set(result.bodies) == set(LAYOUTS)
    head = result.bodies["head"]
    assert head.spheres_used == 3 and np.array_equal(head.indices < 0, [True, False, False, True, False])
    rotation, translation = pose_error(head.fit.T_world_body, POSES["head"])
    assert rotation < 1e-6 and translation < 1e-9


def twin_triangle(spheres: np.ndarray) -> np.ndarray:
    """``spheres`` (5, 3) with 3 and 4 moved so that triangle (0, 3, 4) repeats the sides of (0, 1, 2): 3 and 4 are
    1 and 2 turned about sphere 0, half a turn about x, then 100 degrees about z."""
    turn = matrix_from_rotvec(np.array([0.0, 0.0, np.radians(100.0)])) @ np.diag([1.0, -1.0, -1.0])
    return np.vstack([spheres[:3], (spheres[1:3] - spheres[0]) @ turn.T + spheres[0]])


def test_a_triangle_whose_sides_the_body_repeats_makes_no_body():
    """Three points that fit two triangles of a body (the same sides) leave its pose ambiguous: no body; on a body
    without the twin triangle the same three points find it."""
    head = LAYOUTS["head"]
    twin = twin_triangle(head)
    triangle = transform_points(POSES["head"], head[:3])
    assert len(body_candidates(twin, triangle, MatchOptions(sparse_width=1e-6))) == 0
    assert "twin" not in match_bodies({"twin": twin}, triangle).bodies
    found = match_bodies({"head": head}, triangle).bodies["head"]
    assert np.array_equal(found.indices, [0, 1, 2, -1, -1])
    assert pose_error(found.fit.T_world_body, POSES["head"])[1] < 1e-9


def test_a_triangle_two_bodies_share_makes_neither():
    """A decoy triangle with no other sphere near, whose sides are a triangle of each of two bodies: neither is
    made, though each alone would be."""
    head = LAYOUTS["head"]
    other = np.vstack([head[:3], LAYOUTS["glove"][3:5] + [0.0, 0.0, 0.1]])
    triangle = transform_points(POSES["glove"], head[:3])
    assert "head" in match_bodies({"head": head}, triangle).bodies
    assert "other" in match_bodies({"other": other}, triangle).bodies
    assert match_bodies({"head": head, "other": other}, triangle).bodies == {}


def test_a_thin_triangle_makes_no_body():
    """Three spheres nearly on one line (the third 10 mm from the line through the others, under ``sparse_width``)
    leave the turn about that line loose: not found from them alone."""
    thin = np.array([[0.0, 0.0, 0.0], [0.12, 0.0, 0.0], [0.05, 0.01, 0.0], [0.02, 0.07, 0.03], [0.09, -0.05, 0.06]])
    triangle = transform_points(POSES["tool"], thin[:3])
    assert match_bodies({"thin": thin}, triangle).bodies == {}
    assert "thin" in match_bodies({"thin": thin}, triangle, options=MatchOptions(sparse_width=0.005)).bodies


def test_two_seen_spheres_lose_the_body():
    rng = np.random.default_rng(2)
    points, truth = scene_points(rng)
    result = match_bodies(LAYOUTS, np.delete(points, truth["glove"][:4], axis=0))
    assert "glove" not in result.bodies and len(result.bodies) == 3


def test_ghosts_alone_make_no_body():
    rng = np.random.default_rng(3)
    ghosts = rng.uniform([-0.8, -0.5, 1.6], [0.8, 0.5, 2.8], (15, 3))
    result = match_bodies(LAYOUTS, ghosts)
    assert result.bodies == {} and np.array_equal(result.unassigned, np.arange(15))


def test_the_choice_is_global_not_greedy_by_body_order():
    """A wand sphere sits where the tool's hidden fourth sphere would be: taking the tool with four spheres
    (its best alone, listed first) would leave the wand without it; the global choice finds both."""
    T_tool = POSES["tool"]
    tool_points = transform_points(T_tool, LAYOUTS["tool"])
    R_wand = matrix_from_rotvec(np.array([1.0, 0.4, -0.2]))
    T_wand = make_transform(R_wand, tool_points[3] - R_wand @ LAYOUTS["wand"][0])
    points = np.concatenate([tool_points[:3], transform_points(T_wand, LAYOUTS["wand"])])
    bodies = {"tool": LAYOUTS["tool"], "wand": LAYOUTS["wand"]}
    alone = body_candidates(LAYOUTS["tool"], points)
    assert alone[0].fit.count == 4
    result = match_bodies(bodies, points)
    assert set(result.bodies) == {"tool", "wand"}
    assert np.array_equal(result.bodies["tool"].indices, [0, 1, 2, -1])
    assert np.array_equal(result.bodies["wand"].indices, [3, 4, 5])
    assert result.unassigned.size == 0


def test_the_gate_rejects_a_bad_fit():
    rng = np.random.default_rng(4)
    points, truth = scene_points(rng)
    points[truth["tool"][0]] += [0.0015, -0.0015, 0.0015]
    assert "tool" in match_bodies(LAYOUTS, points).bodies
    assert "tool" not in match_bodies(LAYOUTS, points, options=MatchOptions(gate_rms=0.0005,
                                                                             allow_missing=False)).bodies


def test_covariances_give_each_fit_a_covariance():
    rng = np.random.default_rng(5)
    points, _ = scene_points(rng, ghosts=3)
    result = match_bodies(LAYOUTS, points, np.tile(np.eye(3) * 1e-8, (len(points), 1, 1)))
    for match in result.bodies.values():
        assert match.fit.covariance is not None and match.fit.covariance.shape == (6, 6)
        assert np.all(np.linalg.eigvalsh(match.fit.covariance) > 0)


@pytest.mark.parametrize(("call", "message"), [
    (lambda: match_bodies(LAYOUTS, np.zeros((4, 2))), r"points_world must have shape \(M, 3\), got \(4, 2\)"),
    (lambda: match_bodies(LAYOUTS, np.zeros((4, 3)), np.zeros((3, 3, 3))), r"covariances must have shape \(4, 3, 3\)"),
    (lambda: match_bodies({"a": np.eye(2, 3)}, np.zeros((4, 3))), "at least 3 spheres"),
    (lambda: MatchOptions(gate_rms=0.0), "gate_rms\n  Input should be greater than 0"),
    (lambda: MatchOptions(max_candidates=0), "max_candidates\n  Input should be greater than or equal to 1"),
])
def test_bad_input_is_refused_with_a_reason(call, message):
    with pytest.raises(ValueError, match=message):
        call()
