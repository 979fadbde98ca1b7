"""The compiled kernels the rigid bodies node runs (numba), loaded or compiled before its first instant.

Compiling them takes about 10 s each on a 2-core VM; numba keeps the machine code in a disk cache (beside the
modules, else ``NUMBA_CACHE_DIR``), from which a process loads them in a few tenths of a second. ``make``
fills the cache when it installs the project and the container image when it is built:
``python -m services.estimation.bodies.kernels``.
"""

from __future__ import annotations

from services.estimation.bodies import fit_kernel
from services.geometry import triangulation_kernel

__all__ = ["warm"]


def warm() -> None:
    """Each kernel run once on a tiny input: compiled, or loaded from the cache."""
    triangulation_kernel.warm()
    fit_kernel.warm()


if __name__ == "__main__":
    warm()
