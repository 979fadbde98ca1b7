"""A real load on the machine: busy processes that hog the cores while a test or benchmark runs."""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
from collections.abc import Iterator

SPIN = "import time\nend = time.monotonic() + {limit}\nwhile time.monotonic() < end:\n    pass\n"


@contextlib.contextmanager
def busy(processes: int | None = None, limit_s: float = 600.0) -> Iterator[list[subprocess.Popen]]:
    """``processes`` Python processes (default: one per core) spinning on a core each while the block runs;
    each stops by itself after ``limit_s`` should the block's owner die, and all are killed when it ends."""
    count = processes or os.cpu_count() or 2
    spinners = [subprocess.Popen([sys.executable, "-c", SPIN.format(limit=limit_s)]) for _ in range(count)]
    try:
        yield spinners
    finally:
        for spinner in spinners:
            spinner.kill()
        for spinner in spinners:
            spinner.wait()
