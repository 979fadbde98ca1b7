"""Rigid body matching with all bodies' interpretation trees grown together, and their pose covariances in
one batch, cross-checked against plain references written here: a recursive search of every assignment,
body by body, and one ``pose_covariance`` per pose."""

import numpy as np
import pytest

from services.estimation.bodies.rigid import (
    MatchOptions,
    _assignments,
    _contested,
    body_candidates,
    match_bodies,
    pairwise_distances,
    width,
)
from services.geometry.absolute_orientation import pose_covariance, pose_covariances
from services.geometry.rotation import matrix_from_rotvec
from services.geometry.se3 import make_transform, transform_points
from services.synthetic.ir_rig import LAYOUTS


def reference_assignments(spheres: np.ndarray, points: np.ndarray, tolerance: float,
                          may_miss: int) -> set[tuple[int, ...]]:
    """Every assignment of ``spheres`` to distinct points (-1: hidden, at most ``may_miss``) whose pairwise
    distances agree with the spheres' within ``tolerance``, and in which every sphere assigned has, for each
    other sphere but ``may_miss``, some point at its distance (the tree's first pruning), by plain search."""
    body, measured = pairwise_distances(spheres), pairwise_distances(points)
    n, m = len(spheres), len(points)

    def placeable(k: int, q: int) -> bool:
        partners = sum(any(abs(measured[p, q] - body[k, s]) <= tolerance for p in range(m))
                       for s in range(n) if s != k)
        return partners >= n - 1 - may_miss

    if sum(not any(placeable(k, q) for q in range(m)) for k in range(n)) > may_miss:
        return set()
    found = set()

    def grow(chosen: tuple[int, ...]) -> None:
        k = len(chosen)
        if k == n:
            found.add(chosen)
            return
        if chosen.count(-1) < may_miss:
            grow((*chosen, -1))
        for q in range(m):
            if q not in chosen and placeable(k, q) and all(
                    abs(measured[p, q] - body[j, k]) <= tolerance for j, p in enumerate(chosen) if p >= 0):
                grow((*chosen, q))

    grow(())
    return found


def scene(rng: np.random.Generator, ghosts: int, hidden: int) -> np.ndarray:
    """World points of every layout at a random pose, ``hidden`` spheres dropped, ``ghosts`` added, shuffled."""
    points = []
    for spheres in LAYOUTS.values():
        T = make_transform(matrix_from_rotvec(rng.normal(0.0, 1.0, 3)), rng.uniform(-0.3, 0.3, 3) + [0, 0, 2])
        points.append(transform_points(T, spheres) + rng.normal(0.0, 2e-4, spheres.shape))
    points = np.concatenate(points)
    points = np.delete(points, rng.choice(len(points), hidden, replace=False), axis=0)
    points = np.vstack([points, rng.uniform([-0.4, -0.4, 1.6], [0.4, 0.4, 2.4], (ghosts, 3))])
    return points[rng.permutation(len(points))]


@pytest.mark.parametrize("seed", range(6))
def test_the_trees_grown_together_give_each_body_every_assignment_of_a_plain_search(seed):
    rng = np.random.default_rng(seed)
    points = scene(rng, ghosts=3, hidden=seed % 3)
    bodies = list(LAYOUTS.values())
    widest = max(len(s) for s in bodies)
    padded = np.zeros((len(bodies), widest, 3))
    for b, spheres in enumerate(bodies):
        padded[b, :len(spheres)] = spheres
    may_miss = [len(s) - 3 if seed % 2 else min(len(s) - 3, 1) for s in bodies]
    owner, assignments = _assignments(padded, [len(s) for s in bodies], pairwise_distances(points), 0.003, may_miss)
    total = 0
    for b, spheres in enumerate(bodies):
        mine = assignments[owner == b]
        assert np.all(mine[:, len(spheres):] == -1)
        got = [tuple(row[:len(spheres)].tolist()) for row in mine]
        expected = reference_assignments(spheres, points, 0.003, may_miss[b])
        assert len(got) == len(set(got)) and set(got) == expected
        total += len(expected)
    assert total >= len(bodies) - 1


@pytest.mark.parametrize("seed", range(4))
def test_an_assignment_is_contested_where_another_holds_its_points_on_other_spheres(seed):
    """``_contested`` against a plain loop over every pair of assignments of the trees of all bodies together, a
    fifth body sharing the head's first triangle."""
    rng = np.random.default_rng(10 + seed)
    points = scene(rng, ghosts=2 + 2 * seed, hidden=0)
    bodies = [*LAYOUTS.values(), np.vstack([LAYOUTS["head"][:3], LAYOUTS["glove"][3:5] + [0.0, 0.0, 0.1]])]
    padded = np.zeros((len(bodies), max(len(s) for s in bodies), 3))
    for b, spheres in enumerate(bodies):
        padded[b, :len(spheres)] = spheres
    owner, assignments = _assignments(padded, [len(s) for s in bodies], pairwise_distances(points), 0.003,
                                      [len(s) - 3 for s in bodies])
    rows = np.arange(len(assignments))
    got = _contested(owner, assignments, rows, len(points))
    expected = []
    for p in rows:
        mine = {(int(i), k) for k, i in enumerate(assignments[p]) if i >= 0}
        expected.append(any(
            q != p and {i for i, _ in mine} <= {int(i) for i in assignments[q] if i >= 0}
            and not (owner[q] == owner[p] and all(assignments[q][k] == i for i, k in mine))
            for q in rows))
    assert got.tolist() == expected and 0 < sum(expected) < len(expected)


def test_width_is_a_triangle_s_least_height():
    rng = np.random.default_rng(3)
    spheres = rng.normal(0.0, 0.05, (50, 5, 3))
    seen = np.zeros((50, 5), bool)
    for row in seen:
        row[rng.choice(5, 3, replace=False)] = True
    expected = []
    for triangle in (spheres[k][seen[k]] for k in range(50)):
        twice_area = np.linalg.norm(np.cross(triangle[1] - triangle[0], triangle[2] - triangle[0]))
        expected.append(twice_area / pairwise_distances(triangle).max())
    np.testing.assert_allclose(width(spheres, seen), expected, rtol=1e-12, atol=0)


def test_batched_pose_covariances_are_each_pose_s_own():
    rng = np.random.default_rng(5)
    transforms, bodies, sigmas, used = [], [], [], []
    for count in (3, 4, 5, 6):
        T = make_transform(matrix_from_rotvec(rng.normal(0.0, 1.0, 3)), rng.normal(0.0, 1.0, 3))
        body = rng.normal(0.0, 0.1, (6, 3))
        a = rng.normal(0.0, 1e-4, (6, 3, 3))
        keep = np.zeros(6, bool)
        keep[rng.choice(6, count, replace=False)] = True
        transforms.append(T)
        bodies.append(body)
        sigmas.append(np.where(keep[:, None, None], a @ a.transpose(0, 2, 1), np.nan))
        used.append(keep)
    batched = pose_covariances(np.array(transforms), np.array(bodies), np.array(sigmas), np.array(used))
    for k in range(len(transforms)):
        alone = pose_covariance(transforms[k], bodies[k][used[k]], sigmas[k][used[k]])
        np.testing.assert_array_equal(batched[k], alone)


def test_chosen_fits_and_candidates_carry_the_covariance_of_their_own_points():
    rng = np.random.default_rng(8)
    points = scene(rng, ghosts=4, hidden=1)
    a = rng.normal(0.0, 3e-4, (len(points), 3, 3))
    covariances = a @ a.transpose(0, 2, 1)
    matching = match_bodies(LAYOUTS, points, covariances)
    assert len(matching.bodies) >= 2
    for name, match in matching.bodies.items():
        seen = match.indices >= 0
        expected = pose_covariance(match.fit.T_world_body, LAYOUTS[name][seen], covariances[match.indices[seen]])
        np.testing.assert_array_equal(match.fit.covariance, expected)
        for candidate in body_candidates(LAYOUTS[name], points, MatchOptions(), covariances):
            seen = candidate.indices >= 0
            np.testing.assert_array_equal(candidate.fit.covariance, pose_covariance(
                candidate.fit.T_world_body, LAYOUTS[name][seen], covariances[candidate.indices[seen]]))
