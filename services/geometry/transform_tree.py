"""One parent per frame: the transforms of a recording arranged as the tree that ``/tf`` readers (Foxglove's 3D
panel, ROS's tf2) need.

artrack's messages name transforms as they are measured, and a frame can be the child of two of them: a
SLAM camera is ``rig -> cam0`` (its place on the rig, from its CameraInfo) and ``map -> cam0`` (its pose in
the map) at once, and a marker seen by two cameras is ``cam0 -> marker/3`` and ``cam1 -> marker/3``. A tree
reader re-parents such a frame back and forth on every message. ``TransformTree`` decides, edge by edge and
in the order the edges come, how each one joins the tree built so far, without changing what it says:

* an edge whose child has no parent yet (and that closes no cycle) is kept as it is;
* an edge whose child has another parent, while its parent frame is the root of another tree, is turned
  round: ``map -> cam0`` becomes ``cam0 -> map`` (the inverse transform), so the map hangs under the camera
  and the camera's pose in the map is still the path between them;
* any other edge keeps its parent and gets a child of its own, ``<parent>/<child>`` (``cam1/marker/3``):
  the second view of the frame stands beside the first.

Only names are decided here; the caller inverts the transform when told to.
"""

from __future__ import annotations

from typing import NamedTuple


class TreeEdge(NamedTuple):
    """How an edge ``parent -> child`` joins the tree: ``parent -> child`` as named here, and whether the
    transform is to be inverted (``T_child_parent`` of the edge as given)."""

    parent: str
    child: str
    inverted: bool


class TransformTree:
    """The frames seen so far, each with its one parent (roots have none)."""

    def __init__(self) -> None:
        self._parent: dict[str, str] = {}

    def parent(self, frame: str) -> str | None:
        """``frame``'s parent in the tree; None for a root or an unknown frame."""
        return self._parent.get(frame)

    def root(self, frame: str) -> str:
        """The root of the tree ``frame`` is in (``frame`` itself when it has no parent)."""
        while (up := self._parent.get(frame)) is not None:
            frame = up
        return frame

    def edge(self, parent: str, child: str) -> TreeEdge:
        """Where the transform ``T_parent_child`` goes in the tree (see the module docstring); the tree keeps it."""
        if self._parent.get(child) == parent:
            return TreeEdge(parent, child, False)
        if self._parent.get(parent) == child:
            return TreeEdge(child, parent, True)
        if child not in self._parent and self.root(parent) != child:
            self._parent[child] = parent
            return TreeEdge(parent, child, False)
        if parent not in self._parent and self.root(child) != parent:
            self._parent[parent] = child
            return TreeEdge(child, parent, True)
        beside = f"{parent}/{child}"
        self._parent[beside] = parent
        return TreeEdge(parent, beside, False)
