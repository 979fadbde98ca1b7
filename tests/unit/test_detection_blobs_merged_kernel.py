"""The compiled code for merged blobs (``merged_kernel``) against libraries and plain NumPy: its Cholesky solve
against ``np.linalg.solve`` and ``cv2.solve``'s refusals, the two-disc model's Jacobian against finite
differences of its residuals, and the waist test against the same rule in NumPy's ``bincount`` and
``maximum.accumulate``. (``test_detection_blobs_split.py`` holds the whole fit against scipy's
``least_squares``.)"""

import cv2
import numpy as np
import pytest

from services.detection.blobs import merged_kernel
from services.detection.blobs.merged_kernel import cholesky_solve, has_waist
from tests.blob_images import disc_image


@pytest.mark.parametrize("size", [1, 3, 7])
def test_the_cholesky_solve_is_numpys_solve_on_positive_definite_matrices(size):
    rng = np.random.default_rng(size)
    for _ in range(20):
        factor = rng.normal(size=(size, size + 2))
        matrix, vector = factor @ factor.T, rng.normal(size=size)
        solved, solution = cholesky_solve(matrix, vector)
        assert solved
        np.testing.assert_allclose(solution, np.linalg.solve(matrix, vector), rtol=1e-9, atol=1e-12)


def test_the_cholesky_solve_refuses_the_matrices_cv2_refuses():
    rng = np.random.default_rng(3)
    rank_two = rng.normal(size=(7, 2))
    for matrix in (-np.eye(7), rank_two @ rank_two.T, np.diag([1.0, 2.0, -1e-3, 4.0, 5.0, 6.0, 7.0])):
        assert not cv2.solve(matrix, np.ones((7, 1)), flags=cv2.DECOMP_CHOLESKY)[0]
        assert not cholesky_solve(matrix, np.ones(7))[0]


def test_the_models_jacobian_is_the_derivative_of_its_residuals():
    """Central differences of the residuals, at every pixel where the left and right differences agree (no
    ramp's end or change of disc within the step), give the Jacobian's rows."""
    rng = np.random.default_rng(0)
    ys, xs = np.mgrid[0:16, 0:20]
    xs, ys = xs.ravel().astype(np.float64), ys.ravel().astype(np.float64)
    values = rng.uniform(0, 120, len(xs))
    for _ in range(10):
        params = np.array([*rng.uniform(5, 9, 2), *rng.uniform(10, 14, 2), *rng.uniform(2, 4, 2), 110.0])
        rows = np.empty((8, len(xs)))
        merged_kernel._model(params, xs, ys, values, rows)
        checked = 0
        for index in range(7):
            step = np.zeros(7)
            step[index] = 1e-6
            ahead, behind = np.empty_like(rows), np.empty_like(rows)
            merged_kernel._model(params + step, xs, ys, values, ahead)
            merged_kernel._model(params - step, xs, ys, values, behind)
            right = (ahead[7] - rows[7]) / 1e-6
            left = (rows[7] - behind[7]) / 1e-6
            smooth = np.abs(right - left) < 1e-3
            np.testing.assert_allclose(rows[index][smooth], ((right + left) / 2)[smooth], atol=1e-3)
            checked += smooth.sum()
        assert checked > 0.95 * 7 * len(xs)


def numpy_waist(weights: np.ndarray, centroid: tuple[float, float], axis: tuple[float, float], depth: float) -> bool:
    """The waist rule (``bright.has_waist``) in NumPy: the profile by ``bincount``, the heaviest slice on each
    side by ``maximum.accumulate``."""
    ys, xs = np.nonzero(weights)
    along = (xs - centroid[0]) * axis[0] + (ys - centroid[1]) * axis[1]
    along -= along.min()
    index = along.astype(np.intp)
    share = along - index
    values = weights[ys, xs]
    size = int(index.max()) + 2
    profile = np.bincount(index, values * (1.0 - share), size) + np.bincount(index + 1, values * share, size)
    if size < 3:
        return False
    left = np.maximum.accumulate(profile)[:-2]
    right = np.maximum.accumulate(profile[::-1])[::-1][2:]
    return bool(np.any(profile[1:-1] < (1.0 - depth) * np.minimum(left, right)))


def test_the_waist_test_is_the_rule_in_numpy():
    rng = np.random.default_rng(5)
    waists = 0
    for _ in range(60):
        radii = rng.uniform(1.5, 5.0, 2)
        angle = rng.uniform(0, np.pi)
        gap = rng.uniform(0.3, 1.1) * radii.sum()
        first = rng.uniform(12, 14, 2)
        second = first + gap * np.array([np.cos(angle), np.sin(angle)])
        weights = disc_image([(*first, radii[0]), (*second, radii[1])], (32, 32), 0).astype(np.float64)
        weights[weights < 8] = 0.0
        centroid = tuple(np.average(np.argwhere(weights)[:, ::-1], axis=0, weights=weights[weights > 0]))
        axis = (float(np.cos(angle)), float(np.sin(angle)))
        for depth in (0.02, 0.05, 0.2):
            expected = numpy_waist(weights, centroid, axis, depth)
            assert has_waist(weights, centroid[0], centroid[1], axis[0], axis[1], depth) == expected
            waists += expected
    assert 20 < waists < 160  # both answers are tried
