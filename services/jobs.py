"""``artrack run``: one job = capture + a named pipeline + recorder/viewer, each its own process.

Order of start: the pipeline's nodes and the recorder/viewer first; once every one of them
is live (plus a moment for their subscriptions to reach the bus), the capture node. When
a finite source ends, the job waits for the pipeline to go quiet (no pipeline node received
anything for ``QUIET_S``), then stops every node, so the recorder closes its file with
everything in it. A live source runs until SIGINT/SIGTERM.
"""

from __future__ import annotations

import logging
import signal
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from services.capture.node import Params as CaptureParams
from services.capture.sources import camera_names
from services.catalog import kind
from services.launch import node_command
from services.observe import node_states, wait_for_nodes
from services.runtime.bus import BusConfig, open_session
from services.runtime.supervisor import ProcessSpec, Supervisor

log = logging.getLogger(__name__)

SETTLE_S = 0.5
QUIET_S = 1.0
SINKS = ("recorder", "viewer")
"""Nodes that take in everything, stats included, so never go quiet: left out of the drain."""
DRAIN_LIMIT_S = 10.0
START_LIMIT_S = 30.0

PIPELINES: dict[str, Callable[[list[str]], dict[str, tuple[str, dict[str, Any]]]]] = {
    "capture": lambda cameras: {},
    "echo": lambda cameras: {f"echo-{camera}": ("echo", {"camera": camera}) for camera in cameras},
}
"""Pipeline name -> the nodes it runs for the given cameras: ``{node name: (kind, params)}``."""


class JobError(ValueError):
    """A job that cannot start as asked; the message says why."""


def job_nodes(pipeline: str, capture: CaptureParams, record: Path | None, rerun: Path | None
              ) -> tuple[dict[str, tuple[str, dict[str, Any]]], tuple[str, dict[str, Any]]]:
    """The job's downstream nodes and its capture node, all parameters validated."""
    if pipeline not in PIPELINES:
        raise JobError(f"unknown pipeline {pipeline!r} (known: {', '.join(sorted(PIPELINES))})")
    cameras = list(capture.cameras) or camera_names(capture.source, capture.scene)
    nodes = PIPELINES[pipeline](cameras)
    if record is not None:
        nodes["recorder"] = ("recorder", {"out": str(record)})
    if rerun is not None:
        nodes["viewer"] = ("viewer", {"rrd": str(rerun)})
    for node_kind, params in nodes.values():
        kind(node_kind).params(params)
    return nodes, ("capture", capture.model_dump(mode="json", exclude_defaults=True))


def run_job(bus: BusConfig, pipeline: str, capture: CaptureParams, record: Path | None = None,
            rerun: Path | None = None) -> int:
    """Run the job to the end of its source (or a signal); 0 when every node ended cleanly."""
    nodes, (capture_kind, capture_params) = job_nodes(pipeline, capture, record, rerun)
    stop = threading.Event()
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda *_: stop.set())
    env = bus.to_env()
    downstream = [ProcessSpec(name, node_command(k, name, p), env) for name, (k, p) in nodes.items()]
    source = ProcessSpec("capture", node_command(capture_kind, "capture", capture_params), env, restart=False)
    session = open_session(bus)
    supervisor = Supervisor(downstream)
    try:
        supervisor.start()
        live = wait_for_nodes(session, bus.keys, set(nodes), START_LIMIT_S)
        if live != set(nodes):
            log.error("nodes %s did not come up within %.0f s", sorted(set(nodes) - live), START_LIMIT_S)
            return 1
        time.sleep(SETTLE_S)
        source_supervisor = Supervisor([source])
        source_supervisor.start()
        log.info("job %s: capture from %s", pipeline, ", ".join(capture.source))
        while not stop.is_set() and source_supervisor.step():
            supervisor.step()
            stop.wait(0.05)
        code = source_supervisor.exit_codes().get("capture")
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
