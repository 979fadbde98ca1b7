"""Compiled code of a node kind (numba), loaded from numba's disk cache or compiled there before a node needs it.

Compiling a kernel takes seconds to tens of seconds on a 2-core VM; numba keeps the machine code in a disk cache
(beside the modules, else ``NUMBA_CACHE_DIR``), from which a process loads it in under a second.
A kind's ``NodeKind.prepare`` calls ``prepare`` with the function that runs its kernels once: the launcher's
preflight runs it before any process starts, and ``python -m services.launcher.kernels`` (run by ``make`` and
by the container image's build) for every kind at once.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor, TimeoutError

__all__ = ["LOADED_S", "prepare"]

log = logging.getLogger(__name__)
LOADED_S = 3.0
"""Longer than loading kernels from the cache takes, even on a busy 2-core machine (0.6-0.8 s idle there, most of
it numba's own start): past it they are being compiled (10 s to a minute)."""


def prepare(warm: Callable[[], None], what: str) -> None:
    """Run ``warm`` (each kernel once on a tiny input: loaded, or compiled into the cache), saying that ``what``
    is being compiled when it takes longer than ``LOADED_S``."""
    with ThreadPoolExecutor(1) as pool:
        done = pool.submit(warm)
        try:
            done.result(LOADED_S)
        except TimeoutError:
            log.info("compiling %s into numba's cache (once per machine, up to a minute)", what)
            done.result()
