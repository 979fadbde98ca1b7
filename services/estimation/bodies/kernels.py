"""The compiled kernels the rigid bodies node runs (numba), loaded or compiled before its first instant.

Compiling them takes about 10 s each on a 2-core VM; numba keeps the machine code in a disk cache (beside the
modules, else ``NUMBA_CACHE_DIR``), from which a process loads them in a few tenths of a second. ``make``
fills the cache when it installs the project and the container image when it is built:
``python -m services.estimation.bodies.kernels``; otherwise the launcher's preflight does
(``NodeKind.prepare``), before the node starts.
"""

from __future__ import annotations

import logging
from concurrent.futures import ThreadPoolExecutor, TimeoutError

from services.estimation.bodies import fit_kernel
from services.geometry import triangulation_kernel

__all__ = ["prepare", "warm"]

log = logging.getLogger(__name__)
LOADED_S = 1.0
"""Longer than loading the kernels from the cache takes: past it they are being compiled."""


def warm() -> None:
    """Each kernel run once on a tiny input: compiled, or loaded from the cache."""
    triangulation_kernel.warm()
    fit_kernel.warm()


def prepare() -> None:
    """``warm``, saying so when it compiles (the cache lacks the kernels), which takes about 20 s."""
    with ThreadPoolExecutor(1) as pool:
        done = pool.submit(warm)
        try:
            done.result(LOADED_S)
        except TimeoutError:
            log.info("compiling the rigid bodies node's kernels into numba's cache (once per machine, about 20 s)")
            done.result()


if __name__ == "__main__":
    warm()
