"""A job assembled from what ``artrack run TRACKER`` was asked: the one place a request becomes a pipeline.

The command line turns argv into a ``JobRequest`` (the source's and the tracker's options as given,
the files to write, the flow asked, and how to settle the bus over defaults); ``assemble`` turns it
into the bus and the ``PipelineSpec`` that ``run_job`` runs or ``save_pipeline`` writes. A
``recording:`` source is replayed (on its own rig, or on the one the bus settings ask for); any other
source is a capture node. A synthetic source's fixtures fill the tracker's options that were not
given (``services.launcher.fixtures``): a markers scene's marker length and dictionary, the ``ir_rig``
scene's bodies file, the ``planar_target`` scene's target in a library of its own; and a target named
``synthetic:SCENE`` is that scene's, in its library. The trackers themselves know no scene.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ValidationError

from services.bus.session import BusConfig
from services.launcher.fixtures import scene_settings, scene_target_library
from services.launcher.flags import Flag, explain
from services.launcher.flow import FlowSettings
from services.launcher.job import RECORDING_SCHEME, JobError, JobFile, Recording, build_job
from services.launcher.kinds import kind
from services.launcher.pipeline import NodeSpec, PipelineSpec
from services.launcher.tracker import Tracker

log = logging.getLogger("artrack")

CAPTURE = "capture"
"""The node kind whose options ``artrack run`` takes as the source's (``--source``, ``--fps``, ...)."""


@dataclass(frozen=True)
class JobRequest:
    """``artrack run TRACKER`` as asked: ``source`` the capture options given ({field key: value}),
    ``scene`` a synthetic scene's options as text, ``options`` the tracker's options given, ``flags``
    the tracker's generated flags (to name an option in a message), ``source_flags`` the capture's,
    ``flow`` the flow fields given (``mode``, ``window``), ``record``, ``rerun`` and ``foxglove`` the files to
    write, and ``bus(defaults)`` the bus settings the
    command line and environment give over ``defaults``."""

    tracker: str
    source: dict[str, Any]
    bus: Callable[[Mapping[str, object]], BusConfig]
    scene: dict[str, str] = field(default_factory=dict)
    options: dict[str, Any] = field(default_factory=dict)
    flags: list[Flag] = field(default_factory=list)
    source_flags: list[Flag] = field(default_factory=list)
    record: Path | None = None
    rerun: JobFile | None = None
    foxglove: JobFile | None = None
    flow: dict[str, Any] = field(default_factory=dict)


def assemble(request: JobRequest) -> tuple[BusConfig, PipelineSpec]:
    """The bus and the resolved pipeline of ``request``; JobError (or ValueError) naming what is wrong."""
    uris = request.source.get("source", [])
    if not uris:
        raise JobError("give a --source (camera:N, video:PATH, images:DIR, synthetic:SCENE, rosbag2:DIR or "
                       "recording:PATH.mcap)")
    options = _with_scene_targets(request.options, request.flags)
    if any(uri.startswith(RECORDING_SCHEME) for uri in uris):
        if len(uris) > 1 or len(request.source) > 1 or request.scene:
            raise JobError("a recording is the whole rig: give one --source recording:PATH and no other source "
                           "option")
        recording = Recording.open(uris[0])
        source: NodeSpec | Recording = recording.onto(request.bus(recording.where()))
    else:
        try:
            captured = kind(CAPTURE).validate({**request.source, "scene": request.scene})
        except ValidationError as exc:
            raise ValueError(explain(exc, request.source_flags, "source")) from exc
        source = NodeSpec(kind=CAPTURE, **request.source, **({"scene": request.scene} if request.scene else {}))
        options = _with_scene_fixtures(options, request.flags, captured)
    spec = with_flow(build_job(Tracker.load(request.tracker), source, options, request.flags, request.record,
                               request.rerun, request.foxglove), request.flow)
    return request.bus(spec.bus), spec


def with_flow(spec: PipelineSpec, given: Mapping[str, Any]) -> PipelineSpec:
    """``spec`` with the flow fields ``given`` (``mode``, ``window``; what is not given stays as it was)."""
    if not given:
        return spec
    try:
        flow = FlowSettings.model_validate({**spec.flow.model_dump(), **given})
    except ValidationError as exc:
        raise ValueError("; ".join(f"--{problem['loc'][0]}: {problem['msg']}" for problem in exc.errors())) from exc
    return spec.model_copy(update={"flow": flow})


def _given(options: Mapping[str, Any], name: str) -> bool:
    """Whether the tracker option ``name`` was given (under its field, or ``kind.field`` for a renamed flag)."""
    return any(key.rpartition(".")[2] == name for key in options)


def _with_scene_fixtures(options: dict[str, Any], flags: list[Flag], capture: BaseModel) -> dict[str, Any]:
    """``options`` with what the capture's synthetic sources settle (``scene_settings``) for the tracker's flags,
    where the tracker has a flag for every field of a setting and none was given; each value taken said in
    one line, but for a value the option has by default (nothing to tell)."""
    taken = dict(options)
    for settled in scene_settings(capture.source, capture.scene):  # type: ignore[attr-defined]  # capture Params
        chosen = [flag for flag in flags if flag.field in settled.fields]
        if {flag.field for flag in chosen} != set(settled.fields) or any(_given(options, f) for f in settled.fields):
            continue
        values = settled.values()
        for flag in chosen:
            if flag.field in values and values[flag.field] != flag.info.default:
                taken[flag.key] = value = values[flag.field]
                shown = " ".join(map(str, value)) if isinstance(value, tuple | list) else value
                log.info("using %s %s, as %s renders it (give %s to override)", flag.option, shown, settled.uri,
                         flag.option)
    return taken


def _with_scene_targets(options: dict[str, Any], flags: list[Flag]) -> dict[str, Any]:
    """``options`` with a target named ``synthetic:SCENE[?...]`` made the scene's own, in a library of its own
    (``scene_target_library``)."""
    named = {flag.field: flag for flag in flags if flag.field in ("target", "targets")}
    if set(named) != {"target", "targets"} or named["target"].key not in options:
        return options
    given = options[named["target"].key]
    resolved = scene_target_library([given] if isinstance(given, str) else list(given),
                                    named["targets"].key in options)
    if resolved is None:
        return options
    return {**options, **{named[field].key: value for field, value in resolved.items()}}
