"""``artrack run``: one job = a source + a named pipeline + recorder/viewer, each its own process.

The source is a capture node (any capture URI) or a replay node (``recording:PATH.mcap``:
the cameras' images, calibration and ground truth, restamped with the time they go out, on
the recording's own rig). Order of start: the pipeline's nodes and the recorder/viewer
first; once every one of them is live (plus a moment for their subscriptions to reach the
bus), the source. When a finite source ends, the job waits for the pipeline to go quiet (no
pipeline node received anything for ``QUIET_S``), then stops every node, so the recorder
closes its file with everything in it. A live source runs until SIGINT/SIGTERM.
"""

from __future__ import annotations

import logging
import signal
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from services.bus.discovery import node_states
from services.bus.session import BusConfig, open_session
from services.capture.node import Params as CaptureParams
from services.capture.sources import camera_names
from services.launch import node_command
from services.launcher.kinds import kind
from services.launcher.observe import wait_for_nodes
from services.launcher.supervisor import ProcessSpec, Supervisor
from services.pipelines import PIPELINES, NodeSet
from services.recorder.info import summarise
from services.recorder.reading import NotMcap

log = logging.getLogger(__name__)

SETTLE_S = 0.5
QUIET_S = 1.0
SINKS = ("recorder", "viewer")
"""Nodes that take in everything, stats included, so never go quiet: left out of the drain."""
DRAIN_LIMIT_S = 10.0
START_LIMIT_S = 30.0
RECORDING_SCHEME = "recording:"
REPLAYED_STREAMS = ("image", "camera_info", "truth")

@dataclass(frozen=True)
class Recording:
    """A recorded session as a job's source: its cameras and the rig it was recorded on."""

    path: Path
    cameras: tuple[str, ...]
    namespace: str
    rig: str

    @classmethod
    def open(cls, uri: str) -> Recording:
        """The recording named by ``recording:PATH``; JobError when it is missing, not MCAP or has no images."""
        path = Path(uri.removeprefix(RECORDING_SCHEME))
        if not path.is_file():
            raise JobError(f"{uri}: no such recording")
        try:
            info = summarise(path)
        except NotMcap as exc:
            raise JobError(f"{uri}: {exc}") from exc
        where = info.metadata.get("artrack.recording", {})
        if "namespace" not in where or "rig" not in where:
            raise JobError(f"{uri}: not an artrack recording (no artrack.recording metadata)")
        prefix = f"{where['namespace']}/{where['rig']}/"
        cameras = tuple(sorted({c.key.removeprefix(prefix).rsplit("/", 1)[0] for c in info.channels
                                if c.key.startswith(prefix) and c.key.endswith("/image")}))
        if not cameras:
            raise JobError(f"{uri}: no camera images in it")
        return cls(path, cameras, where["namespace"], where["rig"])

    def on_bus(self, bus: BusConfig) -> BusConfig:
        """``bus`` moved to the recording's namespace and rig, where its keys are replayed."""
        return bus.model_copy(update={"namespace": self.namespace, "rig": self.rig})

    def node(self) -> tuple[str, dict[str, Any]]:
        keys = [f"{camera}/{stream}" for camera in self.cameras for stream in REPLAYED_STREAMS]
        return "replay", {"path": str(self.path), "keys": keys, "restamp": True}


class JobError(ValueError):
    """A job that cannot start as asked; the message says why."""


def job_nodes(pipeline: str, source: CaptureParams | Recording, options: dict[str, Any], record: Path | None,
              rerun: Path | None) -> tuple[NodeSet, tuple[str, dict[str, Any]]]:
    """The job's downstream nodes and its source node, all parameters validated."""
    if pipeline not in PIPELINES:
        raise JobError(f"unknown pipeline {pipeline!r} (known: {', '.join(sorted(PIPELINES))})")
    chosen = PIPELINES[pipeline]
    unknown = sorted(set(options) - set(chosen.options))
    if unknown:
        takes = ", ".join(f"--{o.replace('_', '-')}" for o in chosen.options) or "no options"
        raise JobError(f"pipeline {pipeline!r} does not take {', '.join(unknown)} (it takes {takes})")
    if isinstance(source, Recording):
        cameras, source_node = list(source.cameras), source.node()
    else:
        cameras = list(source.cameras) or camera_names(source.source, source.scene)
        source_node = ("capture", source.model_dump(mode="json", exclude_defaults=True))
    nodes = chosen.nodes(cameras, options)
    if record is not None:
        nodes["recorder"] = ("recorder", {"out": str(record)})
    if rerun is not None:
        nodes["viewer"] = ("viewer", {"rrd": str(rerun)})
    for node_kind, params in [*nodes.values(), source_node]:
        kind(node_kind).params(params)
    return nodes, source_node


def run_job(bus: BusConfig, pipeline: str, source: CaptureParams | Recording, options: dict[str, Any] | None = None,
            record: Path | None = None, rerun: Path | None = None) -> int:
    """Run the job to the end of its source (or a signal); 0 when every node ended cleanly."""
    nodes, (source_kind, source_params) = job_nodes(pipeline, source, options or {}, record, rerun)
    if isinstance(source, Recording):
        bus = source.on_bus(bus)
    stop = threading.Event()
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda *_: stop.set())
    env = bus.to_env()
    downstream = [ProcessSpec(name, node_command(k, name, p), env) for name, (k, p) in nodes.items()]
    origin = ProcessSpec(source_kind, node_command(source_kind, source_kind, source_params), env, restart=False)
    session = open_session(bus)
    supervisor = Supervisor(downstream)
    try:
        supervisor.start()
        live = wait_for_nodes(session, bus.keys, set(nodes), START_LIMIT_S)
        if live != set(nodes):
            log.error("nodes %s did not come up within %.0f s", sorted(set(nodes) - live), START_LIMIT_S)
            return 1
        time.sleep(SETTLE_S)
        source_supervisor = Supervisor([origin])
        source_supervisor.start()
        log.info("job %s on %s: %s from %s", pipeline, bus.keys.prefix, source_kind,
                 source.path if isinstance(source, Recording) else ", ".join(source.source))
        while not stop.is_set() and source_supervisor.step():
            supervisor.step()
            stop.wait(0.05)
        code = source_supervisor.exit_codes().get(source_kind)
        source_supervisor.stop()
        if not stop.is_set():
            _drain(session, bus, set(nodes) - set(SINKS))
        return 0 if stop.is_set() or code == 0 else 1
    finally:
        supervisor.stop()
        session.close()


def _drain(session, bus: BusConfig, names: set[str]) -> None:
    """Wait until no node of ``names`` has received anything for QUIET_S (at most DRAIN_LIMIT_S)."""
    deadline = time.monotonic() + DRAIN_LIMIT_S
    last, quiet_since = None, time.monotonic()
    while time.monotonic() < deadline:
        states = node_states(session, bus.keys, 0.5)
        received = {name: s.received for (rig, name), s in states.items() if rig == bus.rig and name in names}
        if received != last:
            last, quiet_since = received, time.monotonic()
        elif time.monotonic() - quiet_since >= QUIET_S:
            return
        time.sleep(0.1)
