"""Bodies fitted to labelled points, all in one batch: the same fits as one body at a time."""

import numpy as np

from services.estimation.bodies.rigid import MatchOptions, fit_labelled
from services.geometry.absolute_orientation import fit_rigid
from services.geometry.rotation import matrix_from_rotvec
from services.geometry.se3 import make_transform, transform_points
from services.synthetic.ir_rig import LAYOUTS


def fit_alone(spheres, points, covariances, indices, options, min_spheres):
    """One body: fitted to its labelled points; while the fit breaks the gate, the sphere whose absence leaves the
    smallest residual RMS is let go (with three, the first)."""
    indices = indices.copy()
    while np.count_nonzero(indices >= 0) >= min_spheres:
        seen = np.flatnonzero(indices >= 0)
        fit = fit_rigid(spheres[seen], points[indices[seen]], covariances[indices[seen]])
        if fit.residual_rms <= gate(spheres[seen], options):
            return indices, fit
        if len(seen) == 3:
            indices[seen[0]] = -1
            continue
        rest = [np.delete(seen, k) for k in range(len(seen))]
        best = min(rest, key=lambda kept: fit_rigid(spheres[kept], points[indices[kept]]).residual_rms)
        indices[np.setdiff1d(seen, best)] = -1
    return None


def gate(spheres, options):
    """The largest residual RMS of a fit on ``spheres`` (K, 3): ``gate_rms``, and on three spheres no more than
    ``three_turn_deg`` times the distance from one to the line through the other two (the largest such)."""
    if len(spheres) > 3:
        return options.gate_rms
    heights = [np.linalg.norm(np.cross(spheres[(k + 1) % 3] - spheres[k], spheres[(k + 2) % 3] - spheres[k]))
               / np.linalg.norm(spheres[(k + 1) % 3] - spheres[k]) for k in range(3)]
    return min(options.gate_rms, np.radians(options.three_turn_deg) * min(heights))


def test_batched_fits_are_those_of_one_body_at_a_time():
    rng = np.random.default_rng(7)
    for trial in range(40):
        points, labels = [], {}
        for name, spheres in LAYOUTS.items():
            T = make_transform(matrix_from_rotvec(rng.normal(0, 1, 3)), rng.uniform(-0.5, 0.5, 3) + [0, 0, 2])
            world = transform_points(T, spheres) + rng.normal(0, 2e-4, spheres.shape)
            wrong = rng.random(len(spheres)) < 0.2
            world[wrong] += rng.normal(0, 0.004, (int(wrong.sum()), 3))
            label = np.arange(len(points), len(points) + len(spheres))
            label[rng.random(len(spheres)) < 0.15] = -1
            labels[name] = label
            points.extend(world)
        points = np.array(points)
        covariances = np.einsum("nij,nkj->nik", *(2 * [rng.normal(0, 1e-4, (len(points), 3, 3))]))
        options = MatchOptions()
        batched = fit_labelled(LAYOUTS, points, covariances, labels, options, 3)
        for name, spheres in LAYOUTS.items():
            alone = fit_alone(spheres, points, covariances, labels[name], options, 3)
            assert (alone is None) == (name not in batched), (trial, name)
            if alone is None:
                continue
            indices, fit = alone
            match = batched[name]
            assert np.array_equal(match.indices, indices)
            np.testing.assert_allclose(match.fit.T_world_body, fit.T_world_body, rtol=0, atol=1e-12)
            np.testing.assert_allclose(match.fit.covariance, fit.covariance, rtol=1e-9, atol=1e-20)
            assert abs(match.fit.residual_rms - fit.residual_rms) < 1e-12 and match.fit.count == fit.count


def test_a_point_far_off_its_sphere_is_the_one_let_go():
    """One labelled point 8 mm off its sphere (a view of the sphere biased by a blob it merged with): the joint fit
    spreads that error over every sphere, so its largest residual may lie at a good one; the point that goes is
    the one whose absence leaves the best fit, and the body is fitted on the others."""
    rng = np.random.default_rng(11)
    for trial in range(200):
        name = ("tool", "head")[trial % 2]
        spheres = LAYOUTS[name]
        T = make_transform(matrix_from_rotvec(rng.normal(0, 1, 3)), rng.uniform(-0.5, 0.5, 3) + [0, 0, 2])
        points = transform_points(T, spheres) + rng.normal(0, 5e-5, spheres.shape)
        off = int(rng.integers(len(spheres)))
        direction = rng.normal(0, 1, 3)
        points[off] += 0.008 * direction / np.linalg.norm(direction)
        match = fit_labelled({name: spheres}, points, None, {name: np.arange(len(spheres))}, MatchOptions(), 3)[name]
        assert match.indices[off] == -1 and match.spheres_used == len(spheres) - 1, (trial, match.indices)
        assert np.linalg.norm(match.fit.T_world_body[:3, 3] - T[:3, 3]) < 5e-4, trial
