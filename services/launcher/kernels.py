"""``python -m services.launcher.kernels``: every node kind's compiled code built into numba's cache (each
declared kind's ``NodeKind.prepare``, once), so that no node compiles it while its frames wait. ``make`` runs
it as it installs the project, and the container image as it is built."""

from __future__ import annotations

from services.launcher.kinds import catalogue, kind


def prepare_all() -> list[str]:
    """Run the ``prepare`` of every declared kind that has one; the names of those kinds."""
    prepared = []
    for name in sorted(catalogue().kinds):
        node_kind = kind(name)
        if node_kind.prepare is not None:
            node_kind.prepare()
            prepared.append(name)
    return prepared


if __name__ == "__main__":
    prepare_all()
