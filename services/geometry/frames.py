"""A graph of named frames joined by rigid transforms, like ROS ``tf_static``.

Each edge is added once as ``T_parent_child`` ((4, 4) float64, maps child coordinates into
the parent frame); its inverse is derived when a path walks the edge the other way. Any
two connected frames can be looked up: ``transform(a, b)`` finds the path between them
(breadth-first over the undirected graph) and composes ``T_a_b = T_a_f1 @ T_f1_f2 @ ... @ T_fn_b``.

Cycles: the graph is kept a forest. Adding an edge between two frames that are already
connected does not store it; it is checked against the transform the graph already implies
and refused with ``InconsistentCycleError`` when the two differ by more than the graph's
tolerances (rotation angle in radians, translation distance in metres). So the same
transform arriving twice (two publishers, a repeated message) is accepted, and a
contradiction is reported instead of being silently resolved one way or the other.
"""

from __future__ import annotations

from collections import deque

import numpy as np

from services.geometry.rotation import rotation_angle
from services.geometry.se3 import check_transform, invert

__all__ = ["DisconnectedFramesError", "FrameError", "FrameGraph", "InconsistentCycleError", "UnknownFrameError"]


class FrameError(ValueError):
    """A frame graph cannot do what was asked; the message names the frames and why."""


class UnknownFrameError(FrameError):
    """A frame name the graph has never been given."""


class DisconnectedFramesError(FrameError):
    """Two known frames with no chain of transforms between them."""


class InconsistentCycleError(FrameError):
    """A new edge closes a cycle whose transforms disagree beyond the tolerance."""


class FrameGraph:
    """Named frames and the static transforms between them (see the module docstring).

    ``tolerance_rad`` and ``tolerance_m`` bound how far an edge that closes a cycle may differ
    from the transform already implied (rotation angle, translation distance).
    """

    def __init__(self, tolerance_rad: float = 1e-6, tolerance_m: float = 1e-6):
        self.tolerance_rad = tolerance_rad
        self.tolerance_m = tolerance_m
        self._edges: dict[tuple[str, str], np.ndarray] = {}
        self._neighbours: dict[str, list[str]] = {}

    def add(self, parent: str, child: str, T_parent_child: np.ndarray) -> None:
        """Add the edge ``T_parent_child``: (4, 4) float64 rigid transform, child frame -> parent frame.

        New frame names are created. When ``parent`` and ``child`` are already connected the edge
        is only checked (``InconsistentCycleError`` if it disagrees), not stored.
        """
        for frame in (parent, child):
            if not isinstance(frame, str) or not frame:
                raise FrameError(f"frame names must be non-empty strings, got {frame!r}")
        if parent == child:
            raise FrameError(f"an edge needs two different frames, got {parent!r} twice")
        T = check_transform(T_parent_child, f"T_{parent}_{child}").copy()
        if parent in self._neighbours and child in self._neighbours and self._connected(parent, child):
            self._check_agrees(parent, child, T)
            return
        T.setflags(write=False)
        self._edges[(parent, child)] = T
        self._neighbours.setdefault(parent, []).append(child)
        self._neighbours.setdefault(child, []).append(parent)

    def frames(self) -> list[str]:
        """Every frame name, in the order each first appeared."""
        return list(self._neighbours)

    def edges(self) -> list[tuple[str, str, np.ndarray]]:
        """The stored edges ``(parent, child, T_parent_child (4, 4))`` in the order they were added."""
        return [(parent, child, T.copy()) for (parent, child), T in self._edges.items()]

    def __contains__(self, frame: object) -> bool:
        return frame in self._neighbours

    def path(self, a: str, b: str) -> list[str]:
        """The frames from ``a`` to ``b``, both included (``[a]`` when they are the same frame).

        Raises ``UnknownFrameError`` for a name never added, ``DisconnectedFramesError`` when no
        chain of edges joins them.
        """
        self._known(a)
        self._known(b)
        came_from = self._search(a, b)
        if b not in came_from:
            raise DisconnectedFramesError(
                f"no transform chain from frame {a!r} to frame {b!r}: {a!r} is connected to "
                f"{_listed(came_from)}, {b!r} to {_listed(self._search(b, None))}")
        path = [b]
        while path[-1] != a:
            path.append(came_from[path[-1]])
        return path[::-1]

    def transform(self, a: str, b: str) -> np.ndarray:
        """``T_a_b``: (4, 4) float64, maps coordinates in frame ``b`` to frame ``a`` (identity for a == b)."""
        path = self.path(a, b)
        T = np.eye(4)
        for here, there in zip(path, path[1:], strict=False):
            T = T @ self._step(here, there)
        return T

    def _step(self, here: str, there: str) -> np.ndarray:
        """``T_here_there`` of one edge, stored either way round."""
        stored = self._edges.get((here, there))
        return stored if stored is not None else invert(self._edges[(there, here)])

    def _search(self, start: str, goal: str | None) -> dict[str, str]:
        """Breadth-first from ``start``: frame -> the frame it was reached from (``start`` maps to itself)."""
        came_from = {start: start}
        queue = deque([start])
        while queue and goal not in came_from:
            here = queue.popleft()
            for there in self._neighbours[here]:
                if there not in came_from:
                    came_from[there] = here
                    queue.append(there)
        return came_from

    def _connected(self, a: str, b: str) -> bool:
        return b in self._search(a, b)

    def _check_agrees(self, parent: str, child: str, T_parent_child: np.ndarray) -> None:
        implied = self.transform(parent, child)
        angle = rotation_angle(implied[:3, :3], T_parent_child[:3, :3])
        distance = float(np.linalg.norm(implied[:3, 3] - T_parent_child[:3, 3]))
        if angle > self.tolerance_rad or distance > self.tolerance_m:
            raise InconsistentCycleError(
                f"T_{parent}_{child} disagrees with the chain {' -> '.join(self.path(parent, child))} already "
                f"known: rotation off by {angle:.3g} rad (tolerance {self.tolerance_rad:.3g}), translation off by "
                f"{distance:.3g} m (tolerance {self.tolerance_m:.3g})")

    def _known(self, frame: str) -> None:
        if frame not in self._neighbours:
            raise UnknownFrameError(f"unknown frame {frame!r} (known: {_listed(self._neighbours)})")


def _listed(frames) -> str:
    names = sorted(frames)
    return ", ".join(repr(name) for name in names) if names else "none"
