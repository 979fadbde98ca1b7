"""``check_transform`` against the rule it states, written with numpy's matrix product and determinant."""

from __future__ import annotations

import numpy as np
import pytest

from services.geometry.rotation import matrix_from_rotvec
from services.geometry.se3 import check_transform, make_transform

TOLERANCE = 1e-6


def numpy_verdict(T: np.ndarray, tolerance: float = TOLERANCE) -> str | None:
    """Which part of the rule ``T`` breaks first, by numpy: None when it is a proper rigid transform."""
    if not np.all(np.isfinite(T)):
        return "finite"
    if np.max(np.abs(T[3] - (0.0, 0.0, 0.0, 1.0))) > tolerance:
        return "last row"
    R = T[:3, :3]
    if np.max(np.abs(R.T @ R - np.eye(3))) > tolerance:
        return "orthonormal"
    if abs(np.linalg.det(R) - 1.0) > tolerance:
        return "proper rotation"
    return None


def verdict(T: np.ndarray) -> str | None:
    try:
        check_transform(T)
    except ValueError as error:
        return next(part for part in ("finite", "last row", "orthonormal", "proper rotation") if part in str(error))
    return None


def spoiled(rng: np.random.Generator, T: np.ndarray, how: str) -> np.ndarray:
    """``T`` made improper (or kept) in one of a few ways, by amounts on both sides of the tolerance."""
    T = T.copy()
    size = 10.0 ** rng.uniform(-9, -2)
    if how == "scaled":
        T[:3, :3] *= 1 + size
    elif how == "sheared":
        T[rng.integers(3), rng.integers(3)] += size
    elif how == "reflected":
        T[:3, rng.integers(3)] *= -1
    elif how == "projective":
        T[3, rng.integers(4)] += size
    elif how == "nan":
        T[rng.integers(4), rng.integers(4)] = rng.choice([np.nan, np.inf, -np.inf])
    return T


@pytest.mark.parametrize("how", ["kept", "scaled", "sheared", "reflected", "projective", "nan"])
def test_the_verdicts_are_numpys_for_transforms_spoiled_every_way(how):
    rng = np.random.default_rng(len(how))
    verdicts = []
    for _ in range(400):
        T = make_transform(matrix_from_rotvec(rng.normal(0.0, 1.5, 3)), rng.uniform(-5.0, 5.0, 3))
        T = spoiled(rng, T, how)
        expected = numpy_verdict(T)
        assert verdict(T) == expected, (how, T)
        verdicts.append(expected)
    if how == "kept":
        assert set(verdicts) == {None}
    elif how in ("scaled", "sheared", "projective"):
        assert None in verdicts and len(set(verdicts)) >= 2, set(verdicts)
    else:
        assert None not in verdicts


def test_the_errors_name_the_transform_and_the_figures():
    T = make_transform(np.eye(3), (1.0, 2.0, 3.0))
    T[3, 0] = 0.5
    with pytest.raises(ValueError, match=r"^T_a_b must have last row \(0, 0, 0, 1\), got \(0.5, 0.0, 0.0, 1.0\)$"):
        check_transform(T, "T_a_b")
    T = make_transform(np.diag([1.0, 1.0, -1.0]), (0.0, 0.0, 0.0))
    with pytest.raises(ValueError, match=r"det \+1\), got det -1$"):
        check_transform(T, "T_a_b")
    T = make_transform(np.eye(3) * 1.01, (0.0, 0.0, 0.0))
    with pytest.raises(ValueError, match=r"off by 0.0201$"):
        check_transform(T, "T_a_b")
    with pytest.raises(ValueError, match="must have shape"):
        check_transform(np.eye(3), "T_a_b")


def test_a_transform_given_as_lists_comes_back_as_a_float64_array():
    T = make_transform(matrix_from_rotvec(np.array([0.3, -0.2, 0.1])), (1.0, 2.0, 3.0))
    checked = check_transform(T.tolist())
    assert checked.dtype == np.float64 and np.array_equal(checked, T)
