"""The centroid noise estimated from reprojection residuals: a known sigma recovered, robust to wrong points."""

import cv2
import numpy as np
import pytest

from services.estimation.bodies.centroid_noise import (
    CentroidNoise,
    _chi2_constants,
    _chi2_table,
    _median,
    degrees_of_freedom,
    robust_variance,
)
from services.geometry.camera import CameraModel
from services.geometry.triangulation import reproject, triangulate


def simulated(rng: np.random.Generator, count: int, views: np.ndarray,
              sigma_px: float) -> tuple[np.ndarray, np.ndarray]:
    """(count,) rms_px and views of points whose residuals sum to sigma^2 chi2(2v - 3)."""
    v = rng.choice(views, count)
    squares = sigma_px**2 * rng.chisquare(degrees_of_freedom(v))
    return np.sqrt(squares / v), v


def test_degrees_of_freedom_are_two_per_view_less_three():
    assert degrees_of_freedom(np.array([1, 2, 3, 4])).tolist() == [0, 1, 3, 5]


@pytest.mark.parametrize("sigma_px", [0.012, 0.1, 0.5])
def test_a_known_sigma_is_recovered_from_two_and_three_view_residuals(sigma_px):
    rng = np.random.default_rng(1)
    noise = CentroidNoise(window=100)
    for _ in range(100):
        estimate = noise.update(*simulated(rng, 12, np.array([2, 2, 3]), sigma_px))
    assert estimate == pytest.approx(sigma_px, rel=0.03)


def test_wrong_correspondences_do_not_inflate_the_estimate():
    rng = np.random.default_rng(2)
    rms, views = simulated(rng, 2000, np.array([2]), 0.02)
    rms[:40] = rng.uniform(0.5, 2.0, 40)
    variance = robust_variance(np.square(rms) * views, degrees_of_freedom(views))
    assert variance is not None and np.sqrt(variance) == pytest.approx(0.02, rel=0.04)
    assert np.sqrt(np.mean(np.square(rms) * views)) > 0.1


def test_the_estimate_is_the_prior_until_residuals_come_and_never_below_the_floor():
    noise = CentroidNoise(floor_px=0.005, prior_px=0.1)
    assert noise.update(np.zeros(0), np.zeros(0, np.int64)) == 0.1
    assert noise.update(np.zeros(5), np.full(5, 2)) == 0.005


def test_the_window_forgets_old_sets():
    rng = np.random.default_rng(3)
    noise = CentroidNoise(window=20)
    for _ in range(20):
        noise.update(*simulated(rng, 10, np.array([2]), 0.5))
    for _ in range(20):
        estimate = noise.update(*simulated(rng, 10, np.array([2]), 0.05))
    assert estimate == pytest.approx(0.05, rel=0.15)


@pytest.mark.parametrize("window", [1, 5, 100])
def test_the_running_estimate_is_the_pooled_estimate_of_the_window_s_sets(window):
    rng = np.random.default_rng(window)
    noise = CentroidNoise(window=window, floor_px=0.005, prior_px=0.1)
    sets, expected = [], 0.1
    for _ in range(300):
        count = int(rng.integers(0, 15))
        views = rng.choice([1, 2, 2, 3, 4], count)
        rms = np.abs(rng.normal(0.0, 0.05, count)) * np.where(rng.random(count) < 0.05, 20.0, 1.0)
        if count and rng.random() < 0.1:
            rms[0] = np.inf if rng.random() < 0.5 else 0.0
        estimate = noise.update(rms, views)
        if np.any(views >= 2):
            sets = [*sets, (np.square(rms) * views, degrees_of_freedom(views))][-window:]
        variance = robust_variance(np.concatenate([s for s, _ in sets]), np.concatenate([d for _, d in sets])) \
            if sets else None
        expected = expected if variance is None else max(float(np.sqrt(variance)), 0.005)
        assert estimate == expected


def test_the_residuals_of_triangulated_points_give_back_the_pixel_noise():
    rng = np.random.default_rng(4)
    K = np.array([[800.0, 0, 320], [0, 800, 240], [0, 0, 1]])
    cameras = []
    for k, x in enumerate((-0.4, 0.0, 0.4)):
        T_rig_camera = np.eye(4)
        T_rig_camera[:3, :3] = cv2.Rodrigues(np.array([0.0, -0.15 * x, 0.0]))[0]
        T_rig_camera[0, 3] = x
        cameras.append(CameraModel(name=f"cam{k}", width=640, height=480, K=K, dist=np.zeros(5),
                                   T_rig_camera=T_rig_camera))
    noise = CentroidNoise(window=1)
    rms, views = [], []
    for _ in range(600):
        point = np.array([rng.uniform(-0.3, 0.3), rng.uniform(-0.2, 0.2), rng.uniform(1.5, 2.5)])
        seen = cameras[:int(rng.integers(2, 4))]
        pixels = np.vstack([reproject(c, point) for c in seen]) + rng.normal(0.0, 0.05, (len(seen), 2))
        found = triangulate(seen, pixels, sigma_px=1.0)
        rms.append(found.rms_px)
        views.append(found.views)
    assert noise.update(np.array(rms), np.array(views)) == pytest.approx(0.05, rel=0.05)


def test_bad_settings_are_refused():
    with pytest.raises(ValueError, match="floor_px"):
        CentroidNoise(floor_px=0.0)


@pytest.mark.parametrize("dof", [1, 3, 5, 9])
@pytest.mark.parametrize("keep", [0.9, 0.999])
def test_the_chi2_constants_are_scipy_stats_chi2s(dof, keep):
    """The median, the ``keep`` quantile and the mean below it (numerical integration) of ``scipy.stats.chi2``."""
    from scipy.stats import chi2

    median, limit, share = _chi2_constants(dof, keep)
    assert median == pytest.approx(chi2.median(dof), rel=1e-12)
    assert limit == pytest.approx(chi2.ppf(keep, dof), rel=1e-12)
    assert share == pytest.approx(chi2.expect(args=(dof,), ub=limit, conditional=True), rel=1e-7)


@pytest.mark.parametrize("size", [1, 2, 3, 4, 1299, 1300])
def test_the_median_is_numpys_to_the_bit(size):
    values = np.random.default_rng(size).exponential(0.01, size)
    assert _median(values) == float(np.median(values))


@pytest.mark.parametrize("largest", [1, 15, 16, 40])
def test_the_constants_table_holds_each_dofs_constants(largest):
    table = _chi2_table(largest, 0.999)
    assert table.shape[0] > largest and not table.flags.writeable
    assert all(tuple(table[dof]) == _chi2_constants(dof, 0.999) for dof in range(1, largest + 1))
