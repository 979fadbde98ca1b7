"""The constant-velocity motion model of a rigid body: truth recovered, scipy's Slerp agreed with, gaps reset."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from services.estimation.motion import ConstantVelocity, MotionOptions
from services.geometry.rotation import matrix_from_rotvec
from services.geometry.se3 import make_transform

OMEGA = np.array([0.8, -1.9, 2.6])
VELOCITY = np.array([0.4, -0.25, 0.9])
R_START = matrix_from_rotvec(np.array([0.3, 1.2, -0.7]))
T_START = np.array([0.1, -0.2, 2.3])
STEP_NS = 33_333_333


def truth(stamp_ns: int) -> np.ndarray:
    """(4, 4) T_world_body of a body turning at OMEGA (world frame) about its origin, moving at VELOCITY."""
    s = stamp_ns / 1e9
    return make_transform(matrix_from_rotvec(OMEGA * s) @ R_START, T_START + VELOCITY * s)


def test_a_constant_velocity_is_recovered_and_extrapolated_exactly():
    model = ConstantVelocity()
    assert model.predict(STEP_NS) is None
    model.update(0, truth(0))
    assert not model.ready and model.predict(STEP_NS) is None
    model.update(STEP_NS, truth(STEP_NS))
    omega, v = model.velocity()
    assert np.allclose(omega, OMEGA, atol=1e-9) and np.allclose(v, VELOCITY, atol=1e-12)
    for ahead in (1, 2, 3):
        stamp = STEP_NS * (1 + ahead)
        predicted = model.predict(stamp)
        assert predicted is not None and predicted.stamp_ns == stamp
        assert np.allclose(predicted.T_world_body, truth(stamp), atol=1e-12)


def test_between_its_two_poses_the_model_is_scipys_slerp_and_beyond_them_on_the_same_geodesic():
    model = ConstantVelocity()
    model.update(0, truth(0))
    model.update(STEP_NS, truth(STEP_NS))
    keys = Rotation.from_matrix([truth(0)[:3, :3], truth(STEP_NS)[:3, :3]])
    slerp = Slerp([0.0, 1.0], keys)
    for fraction in (0.0, 0.25, 0.5, 0.9):
        predicted = model.predict(round(fraction * STEP_NS))
        assert predicted is not None
        expected = slerp([fraction]).as_matrix()[0]
        assert np.allclose(predicted.T_world_body[:3, :3], expected, atol=1e-12)
        assert np.allclose(predicted.T_world_body[:3, 3], (1 - fraction) * truth(0)[:3, 3]
                           + fraction * truth(STEP_NS)[:3, 3], atol=1e-12)
    # Extrapolated two steps on, the pose lies on scipy's geodesic from the first pose through the second.
    far = model.predict(2 * STEP_NS)
    assert far is not None
    through = Slerp([0.0, 2.0], Rotation.from_matrix([truth(0)[:3, :3], far.T_world_body[:3, :3]]))
    assert np.allclose(through([1.0]).as_matrix()[0], truth(STEP_NS)[:3, :3], atol=1e-12)


def test_a_gap_longer_than_the_limit_starts_the_motion_afresh():
    model = ConstantVelocity(MotionOptions(max_gap_s=0.1))
    model.update(0, truth(0))
    model.update(STEP_NS, truth(STEP_NS))
    assert model.predict(STEP_NS + 100_000_000) is not None
    assert model.predict(STEP_NS + 100_000_001) is None
    late = STEP_NS + 150_000_000
    still = make_transform(np.eye(3), T_START)
    model.update(late, still)
    assert not model.ready and model.predict(late + STEP_NS) is None
    model.update(late + STEP_NS, still)
    omega, v = model.velocity()
    assert np.allclose(omega, 0.0) and np.allclose(v, 0.0)


def test_the_covariance_grows_with_the_time_predicted_ahead():
    model = ConstantVelocity()
    fit_covariance = np.diag([1e-6, 1e-6, 1e-6, 1e-8, 1e-8, 1e-8])
    model.update(0, truth(0), fit_covariance)
    model.update(STEP_NS, truth(STEP_NS), fit_covariance)
    near, far = model.predict(2 * STEP_NS), model.predict(3 * STEP_NS)
    assert near is not None and far is not None
    assert np.all(np.diag(near.covariance) > 5 * np.diag(fit_covariance))  # (1 + 1)^2 + 1 = 5, plus drift
    assert np.all(np.diag(far.covariance) > np.diag(near.covariance))
    assert np.allclose(near.covariance, near.covariance.T) and np.all(np.linalg.eigvalsh(near.covariance) > 0)


def test_bad_input_is_refused_with_its_reason():
    model = ConstantVelocity()
    model.update(10, truth(0))
    with pytest.raises(ValueError, match="not after the newest"):
        model.update(10, truth(0))
    with pytest.raises(ValueError, match="must be a proper rotation"):
        model.update(20, np.diag([1.0, 1.0, -1.0, 1.0]))
    with pytest.raises(ValueError, match=r"covariance must have shape \(6, 6\), got \(3, 3\)"):
        model.update(20, truth(0), np.eye(3))
    with pytest.raises(ValueError, match="velocity needs two poses"):
        model.velocity()
    with pytest.raises(ValueError, match="max_gap_s\n  Input should be greater than 0"):
        MotionOptions(max_gap_s=0)
