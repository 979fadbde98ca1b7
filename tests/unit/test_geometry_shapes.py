"""The shape check of public functions' arrays: what it accepts, what it refuses and how it says so."""

from __future__ import annotations

import numpy as np
import pytest

from services.geometry.shapes import check_shape


@pytest.mark.parametrize(("shape", "array"), [
    ("N,3", np.zeros((5, 3))),
    ("N,3", np.zeros((0, 3))),
    ("3,3", np.eye(3)),
    ("N,N", np.eye(4)),
    ("*,3,3", np.eye(3)),
    ("*,3,3", np.zeros((2, 7, 3, 3))),
    ("N", [1.0, 2.0]),
    ("", 1.5),
    ("B, N, 2", np.zeros((2, 4, 2))),
])
def test_arrays_of_the_shape_are_accepted_and_returned_as_arrays(shape, array):
    found = check_shape(array, shape)
    assert isinstance(found, np.ndarray) and found.shape == np.shape(array)


def test_an_array_is_returned_as_it_is_or_in_the_dtype_asked():
    points = np.zeros((4, 3), np.float32)
    assert check_shape(points, "N,3") is points
    assert check_shape(points, "N,3", dtype=np.float64).dtype == np.float64
    assert check_shape([[1, 2, 3]], "N,3", dtype=np.float64).dtype == np.float64


@pytest.mark.parametrize(("shape", "array", "message"), [
    ("N,3", np.zeros((4, 2)), r"points must have shape \(N, 3\), got \(4, 2\)"),
    ("N,3", np.zeros(3), r"points must have shape \(N, 3\), got \(3,\)"),
    ("3,3", np.zeros((3, 3, 1)), r"points must have shape \(3, 3\), got \(3, 3, 1\)"),
    ("N,N", np.zeros((3, 4)), r"points must have shape \(N, N\), got \(3, 4\)"),
    ("*,3,3", np.zeros((2, 3, 4)), r"points must have shape \(\*, 3, 3\), got \(2, 3, 4\)"),
    ("*,3,3", np.zeros(9), r"points must have shape \(\*, 3, 3\), got \(9,\)"),
    ("5", np.zeros(4), r"points must have shape \(5,\), got \(4,\)"),
])
def test_other_shapes_are_refused_naming_the_argument_and_both_shapes(shape, array, message):
    with pytest.raises(ValueError, match=message):
        check_shape(array, shape, name="points")


def test_a_malformed_shape_is_refused():
    with pytest.raises(ValueError, match=r"shape '3,\?': '\?' is neither a size nor a name"):
        check_shape(np.zeros(3), "3,?")
    with pytest.raises(ValueError, match="neither a size nor a name"):
        check_shape(np.zeros((3, 3)), "3,*")


@pytest.mark.parametrize("shape", ["N", "N,N", "N,M", "N,M,N", "*,N", "*,N,N", "A,B,C", "*"])
def test_names_and_a_leading_star_agree_with_numpy_einsum(shape):
    """Named sizes mean what einsum's labels mean (a repeated one must match) and ``*`` what its ``...``
    means: for every array of up to three axes of sizes 1 to 3, check_shape accepts exactly the arrays
    einsum takes with those subscripts."""
    subscripts = "".join("..." if name == "*" else name.lower() for name in shape.split(","))
    output = "..." if "*" in shape else ""
    for axes in range(4):
        for sizes in np.ndindex(*(3,) * axes):
            array = np.zeros(tuple(size + 1 for size in sizes))
            try:
                np.einsum(f"{subscripts}->{output}", array)
                taken = True
            except ValueError:
                taken = False
            try:
                check_shape(array, shape)
                accepted = True
            except ValueError:
                accepted = False
            assert accepted == taken, (shape, array.shape)
