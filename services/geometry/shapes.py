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
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import DTypeLike

__all__ = ["check_shape"]


@dataclass(frozen=True)
class _Shape:
    """A parsed shape: ``sizes`` as written, whether a ``*`` leads, the sizes fixed (axis from the end ->
    size) and the axes a recurring name ties together (pairs of axes from the end)."""

    leading: bool
    sizes: tuple[int | str, ...]
    fixed: tuple[tuple[int, int], ...]
    tied: tuple[tuple[int, int], ...]

    def fits(self, actual: tuple[int, ...]) -> bool:
        if len(actual) < len(self.sizes) or (len(actual) > len(self.sizes) and not self.leading):
            return False
        for axis, size in self.fixed:
            if actual[axis] != size:
                return False
        return not self.tied or all(actual[a] == actual[b] for a, b in self.tied)

    def __str__(self) -> str:
        """As a tuple is printed: ``(N, 3)``, ``(N,)``, ``(*, 3, 3)``."""
        parts = ["*"] * self.leading + [str(size) for size in self.sizes]
        return f"({parts[0]},)" if len(parts) == 1 else "(" + ", ".join(parts) + ")"


@functools.cache
def _parse(shape: str) -> _Shape:
    """The parsed ``shape``; ValueError for a malformed one."""
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
    axes = [axis - len(sizes) for axis in range(len(sizes))]
    first: dict[str, int] = {}
    tied = [(first.setdefault(size, axis), axis) for axis, size in zip(axes, sizes, strict=True)
            if isinstance(size, str) and first.setdefault(size, axis) != axis]
    fixed = [(axis, size) for axis, size in zip(axes, sizes, strict=True) if isinstance(size, int)]
    return _Shape(leading, tuple(sizes), tuple(fixed), tuple(tied))


def check_shape(array: Any, shape: str, name: str = "array", dtype: DTypeLike | None = None) -> np.ndarray:
    """``array`` as a numpy array (``np.asarray``, of ``dtype`` when given) once its shape is ``shape``
    (see the module docstring); ValueError naming ``name``, the expected and the actual shape otherwise."""
    found = array if type(array) is np.ndarray and (dtype is None or array.dtype == dtype) \
        else np.asarray(array, dtype=dtype)
    expected = _parse(shape)
    if found.shape != expected.sizes and not expected.fits(found.shape):
        raise ValueError(f"{name} must have shape {expected}, got {found.shape}")
    return found
