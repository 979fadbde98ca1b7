"""What a node kind is: the declaration every node module makes once, next to its ``run``.

A node module ends with::

    KIND = NodeKind(
        name="marker_pose",
        summary="marker and board poses from a camera's frames",
        params=Params,
        run=run,
        inputs=("{camera}/image", "{camera}/camera_info"),
        outputs=("pose/{camera}/**",),
    )

``inputs`` and ``outputs`` are the keys the node reads and writes, relative to the rig prefix
(``ar/<rig>/``), as templates filled from the node's parameters (``{camera}`` is its
``camera`` field), or a function of the parameters when the wiring depends on them. The
launcher finds ``KIND`` by walking the packages it searches (no table lists the kinds), so
``name`` must be a string literal.

``check`` (optional) looks at what the parameters name outside the process, files, folders,
dictionaries, so a launcher can refuse a pipeline before any process starts; it raises
ValueError with one line saying what and why.

A kind's role tells the launcher what it is for a job, so no launcher code names a kind:
``source`` (a ``SourceRole``) for a kind that brings frames onto the bus (whether it ends by
itself, how many frames it will send), ``sink`` (a ``SinkRole``) for one that takes in
everything to write it somewhere (the files it writes).

One more looks across the nodes of a pipeline, where one node's files meet another's frames
(the sizes its sources tell, ``SourceRole.sizes``). ``check_frames``
(optional, a node that may bring a calibration of its own) holds that calibration against those
sizes: it is given the validated parameters and a function that returns ``{camera: (width,
height)}`` of every camera the pipeline's sources told (telling them may read files or build a
scene, so it is called only when there is a calibration to hold), and raises ValueError with one
line when the calibration cannot be used on those frames.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pydantic import BaseModel

from services.runtime.node import Node

Keys = tuple[str, ...] | Callable[[Any], tuple[str, ...]]
"""Key templates (``"{camera}/image"``) or a function of the validated params giving the keys."""
FrameSizes = Mapping[str, tuple[int, int]]
"""``{camera: (width, height)}``: the size of each camera's frames, in pixels."""


@dataclass(frozen=True)
class SourceRole:
    """A kind that brings frames onto the bus, as the launcher sees it (functions of validated params).

    ``finite``: whether the node ends by itself (files, a recording, a scene with a frame count;
    not a camera, an endless scene or a loop). ``frames``: how many frames per camera it will
    send; None when it has no end or that cannot be told before it starts. ``fps``: the pace asked
    (None: the source's own). ``wall_stamps``: whether frames are stamped with the wall-clock time they
    are taken (a camera), so that the rate delivered can be told from the stamps (other sources stamp on
    their own clock, ``services.runtime.stamps``). ``sizes``: the size of
    the frames each of its cameras will send, where the parameters tell it before start (a scene,
    an image folder, a video file, a recording): ``{camera: (width, height)}``, cameras of unknown
    size left out.
    """

    finite: Callable[[Any], bool]
    frames: Callable[[Any], int | None]
    fps: Callable[[Any], float | None]
    wall_stamps: Callable[[Any], bool]
    sizes: Callable[[Any], FrameSizes]


@dataclass(frozen=True)
class SinkRole:
    """A kind that takes in everything on its keys to write it somewhere; ``files(params)``: what it
    writes, as ``(what, path)`` pairs (``("recording", Path("run.mcap"))``)."""

    files: Callable[[Any], tuple[tuple[str, Path], ...]]


@dataclass(frozen=True)
class NodeKind:
    """A kind of node: its name, one-line summary, parameter model, body, declared keys and role."""

    name: str
    summary: str
    params: type[BaseModel]
    run: Callable[[Node, Any], int | None]
    inputs: Keys = ()
    outputs: Keys = ()
    check: Callable[[Any], None] | None = None
    source: SourceRole | None = None
    sink: SinkRole | None = None
    check_frames: Callable[[Any, Callable[[], FrameSizes]], None] | None = None
    prepare: Callable[[], None] | None = None
    """Work done once per machine before a node of the kind starts (compiled code built into its disk cache),
    run by the launcher's preflight so that a node does not do it while frames wait."""

    def validate(self, values: dict[str, Any]) -> BaseModel:
        """Validated parameters (pydantic's ValidationError names the field otherwise)."""
        return self.params.model_validate(values)

    def preflight(self, params: BaseModel) -> None:
        """Run ``check`` on validated ``params`` (ValueError naming the problem); nothing without one."""
        if self.check is not None:
            self.check(params)

    def keys(self, params: BaseModel) -> tuple[tuple[str, ...], tuple[str, ...]]:
        """``(inputs, outputs)`` of a node with ``params``, relative to the rig prefix."""
        return _fill(self.inputs, params), _fill(self.outputs, params)


def _fill(keys: Keys, params: BaseModel) -> tuple[str, ...]:
    if callable(keys):
        return tuple(keys(params))
    values = params.model_dump()
    return tuple(template.format(**values) for template in keys)
