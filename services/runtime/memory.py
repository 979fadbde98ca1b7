"""Memory habits of long-running processes: glibc's thresholds, and the garbage collector's
work on what a node builds at start.

``tune_malloc``: stop glibc from giving payload memory back to the OS after every message.

glibc serves a large ``malloc`` with a fresh ``mmap`` (above 128 KiB at first, a threshold it
then raises to the largest block freed) and trims the top of its heap once more than twice
that threshold lies free. A process that allocates and frees one image-sized buffer per
message (``encode``'s ``bytes``, Zenoh's copy of it) falls into a cycle of returning the
memory and page-faulting it back: minor page faults on every message and a fraction of the
throughput the same code reaches with fixed thresholds (``ARTRACK_MALLOC=default make bench
BENCH=transport`` measures it, docs/benchmarks.md).

Every artrack process fixes the thresholds when it starts (``services.cli.main`` calls
``tune_malloc``), and so do both processes of the benchmarks. Set ``ARTRACK_MALLOC=default``
to keep glibc's defaults.

``settle_heap``: every node calls it once it is up (``services.runtime.node.run_node``).
"""

from __future__ import annotations

import ctypes
import gc
import os

M_TRIM_THRESHOLD = -1
M_MMAP_THRESHOLD = -3
MMAP_THRESHOLD = 32 << 20  # glibc's largest allowed value on 64-bit
TRIM_THRESHOLD = 256 << 20


def tune_malloc() -> str:
    """Fix glibc's mmap and trim thresholds unless told not to; describe the allocator settings in force."""
    if os.environ.get("ARTRACK_MALLOC") == "default":
        return "glibc defaults"
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except AttributeError:
        return "default (no mallopt: not glibc)"
    if not (mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD) and mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD)):
        return "default (mallopt refused the thresholds)"
    return f"mmap_threshold={MMAP_THRESHOLD >> 20} MiB, trim_threshold={TRIM_THRESHOLD >> 20} MiB"


def settle_heap() -> None:
    """Collect once, then leave every object alive now out of later collections (``gc.freeze``).

    A node's start leaves its modules, classes and pydantic schemas behind, long-lived objects
    that every full collection would otherwise walk again, pausing the node for a good part of
    a frame period (the frame behind it is late, and frames that pile up behind it are
    dropped); frozen, they are skipped.
    """
    gc.collect()
    gc.freeze()

