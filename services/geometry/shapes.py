"""The shape check every public function makes of the arrays it is given, as kornia's ``KORNIA_CHECK_SHAPE``.

A shape is written as comma-separated sizes: a number is that size exactly, a name (``N``, ``H``) any
size, the same wherever the name recurs in one shape (``"N,N"``: square), and a leading ``*`` any
number of leading axes, none included (``"*,3,3"``: a 3x3 matrix or a stack of them). ``check_shape(points, "N,3",
name="points")`` returns the array, or raises one ValueError naming the argument, the shape expected
and the shape given::

    points must have shape (N, 3), got (4, 2)
"""

from __future__ import annotations

import functools
from typing import Any

import numpy as np
from numpy.typing import DTypeLike

__all__ = ["check_shape"]


@functools.cache
def _parse(shape: str) -> tuple[bool, tuple[int | str, ...]]:
    """``(leading *, sizes)`` of a written shape; ValueError for a malformed one."""
    tokens = [token.strip() for token in shape.split(",")] if shape.strip() else []
    leading = bool(tokens) and tokens[0] == "*"
    sizes: list[int | str] = []
    for token in tokens[1:] if leading else tokens:
        if token.isdigit():
            sizes.append(int(token))
        elif token.isidentifier():
            sizes.append(token)
        else:
            raise ValueError(f"shape {shape!r}: {token!r} is neither a size nor a name (a leading * only)")
    return leading, tuple(sizes)


def _written(leading: bool, sizes: tuple[int | str, ...]) -> str:
    """A shape as a tuple is printed: ``(N, 3)``, ``(N,)``, ``(*, 3, 3)``."""
    parts = ["*"] * leading + [str(size) for size in sizes]
    return f"({parts[0]},)" if len(parts) == 1 else "(" + ", ".join(parts) + ")"


def check_shape(array: Any, shape: str, name: str = "array", dtype: DTypeLike | None = None) -> np.ndarray:
    """``array`` as a numpy array (``np.asarray``, of ``dtype`` when given) once its shape is ``shape``
    (see the module docstring); ValueError naming ``name``, the expected and the actual shape otherwise."""
    found = np.asarray(array, dtype=dtype)
    leading, sizes = _parse(shape)
    if not _fits(leading, sizes, found.shape):
        raise ValueError(f"{name} must have shape {_written(leading, sizes)}, got {found.shape}")
    return found


def _fits(leading: bool, sizes: tuple[int | str, ...], actual: tuple[int, ...]) -> bool:
    if len(actual) < len(sizes) or (len(actual) > len(sizes) and not leading):
        return False
    bound: dict[str, int] = {}
    for size, given in zip(sizes, actual[len(actual) - len(sizes):], strict=True):
        expected = size if isinstance(size, int) else bound.setdefault(size, given)
        if given != expected:
            return False
    return True
