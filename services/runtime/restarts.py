"""How a supervised process learns it is a restart: the supervisor sets ``ARTRACK_RESTART``.

The supervisor (``services.launcher.supervisor``) starts every child with ``ARTRACK_RESTART``
holding how many times it has restarted that child before: ``0`` the first time, ``1`` after
the first restart, and so on. A node that must not repeat what its killed predecessor did
(the recorder, which never overwrites a file) reads it with ``restart_count``.
"""

from __future__ import annotations

import os

RESTART_ENV = "ARTRACK_RESTART"


def restart_count() -> int:
    """This process's restart number (0: a first start, or not started by a supervisor)."""
    value = os.environ.get(RESTART_ENV, "0")
    try:
        return max(0, int(value))
    except ValueError as exc:
        raise ValueError(f"{RESTART_ENV}={value!r} is not a whole number") from exc
