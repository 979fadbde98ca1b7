"""How a supervised process learns it is a restart (``ARTRACK_RESTART``), and tells that restarting it is no use.

The supervisor (``services.launcher.supervisor``) starts every child with ``ARTRACK_RESTART``
holding how many times it has restarted that child before: ``0`` the first time, ``1`` after
the first restart, and so on. A node that must not repeat what its killed predecessor did
(the recorder, which never overwrites a file) reads it with ``restart_count``.

A child that exits with ``EXIT_CANNOT_RUN`` says it cannot do its job as asked (a node's
``NodeError``), which no restart changes: the supervisor leaves it down.
"""

from __future__ import annotations

import os

RESTART_ENV = "ARTRACK_RESTART"
EXIT_CANNOT_RUN = 2
"""The exit code of a process that cannot do its job as asked (a file it cannot use, a calibration that does not
fit its frames, its name already held on the rig): started again, it would fail alike."""


def restart_count() -> int:
    """This process's restart number (0: a first start, or not started by a supervisor)."""
    value = os.environ.get(RESTART_ENV, "0")
    try:
        return max(0, int(value))
    except ValueError as exc:
        raise ValueError(f"{RESTART_ENV}={value!r} is not a whole number") from exc
