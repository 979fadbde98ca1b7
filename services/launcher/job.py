"""``artrack run``: one job = a source + a tracker's nodes + recorder/viewer, each its own process.

The job is a ``PipelineSpec`` like any pipeline file (``--save-pipeline`` writes it, ``artrack
up`` runs it as a daemon): ``build_job`` fills a tracker template for the source's cameras.
The source is a capture node (any capture URI) or a replay node (``recording:PATH.mcap``:
the cameras' images, calibration and ground truth, restamped with the time they go out, on
the recording's own rig). A job differs from a daemon only in its order and its end: the
nodes that read the bus start first; once every one of them is live (plus a moment for their
subscriptions to reach the bus), the sources (the nodes that read nothing). When the sources
end, the job waits for the pipeline to go quiet (no node received anything for ``QUIET_S``),
then stops every node, so the recorder closes its file with everything in it. A live source
runs until SIGINT/SIGTERM.
"""

from __future__ import annotations

import logging
import signal
import threading
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from services.bus.discovery import node_states
from services.bus.session import BusConfig, open_session
from services.launcher.flags import Flag
from services.launcher.observe import wait_for_nodes
from services.launcher.pipeline import NodeSpec, PipelineSpec, preflight, processes, resolved
from services.launcher.progress import Display, JobWatch
from services.launcher.supervisor import Supervisor
from services.launcher.tracker import Tracker
from services.recorder.info import summarise
from services.recorder.reading import NotMcap
from services.runtime.memory import settle_heap

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


def cameras_of(node: NodeSpec) -> list[str]:
    """The cameras a (resolved) source node publishes images of, from its declared outputs."""
    return [key.removesuffix("/image") for key in node.outputs or () if key.endswith("/image")]


def source_node(source: NodeSpec | Recording) -> tuple[str, NodeSpec]:
    """``(node name, node)`` of a job's source: a source node (capture) as given, or a recording's replay."""
    if isinstance(source, Recording):
        name, params = source.node()
        return name, NodeSpec(kind=name, **params)
    return source.kind, source


def build_job(tracker: Tracker, source: NodeSpec | Recording, options: dict[str, Any], flags: list[Flag],
              record: Path | None = None, rerun: Path | None = None) -> PipelineSpec:
    """The job's pipeline: the source, the tracker's nodes for its cameras, a recorder and a viewer if asked;
    every node validated, its inputs and outputs filled in."""
    name, node = source_node(source)
    where = f"tracker {tracker.name}"
    cameras = cameras_of(resolved(PipelineSpec(nodes={name: node}), where).nodes[name])
    nodes = {name: node, **tracker.expand(cameras, options, flags)}
    if record is not None:
        nodes["recorder"] = NodeSpec(kind="recorder", out=str(record))
    if rerun is not None:
        nodes["viewer"] = NodeSpec(kind="viewer", rrd=str(rerun))
    bus = {"namespace": source.namespace, "rig": source.rig} if isinstance(source, Recording) else {}
    return resolved(PipelineSpec(bus=bus, nodes=nodes), where)


def run_job(bus: BusConfig, spec: PipelineSpec, display: Display | None = None) -> int:
    """Run the job to the end of its sources (or a signal); 0 when every source ended cleanly.

    With ``display``, progress and a summary go where it says (``services.launcher.progress``)."""
    sources = spec.sources()
    if not sources:
        raise JobError("this pipeline has no source (a node that reads nothing): nothing would ever start it")
    preflight(spec, "job")
    downstream = [name for name in spec.nodes if name not in sources]
    stop = threading.Event()
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda *_: stop.set())
    session = open_session(bus)
    watch = _watch(session, bus, spec, display)
    supervisor = Supervisor(processes(spec, bus, downstream))
    try:
        supervisor.start()
        live = wait_for_nodes(session, bus.keys, set(downstream), START_LIMIT_S)
        if live != set(downstream):
            log.error("nodes %s did not come up within %.0f s", sorted(set(downstream) - live), START_LIMIT_S)
            return 1
        time.sleep(SETTLE_S)
        settle_heap()  # this process may be a client too (the demo's): no full collection of its start-up mid-run
        origin = [replace(p, restart=False) for p in processes(spec, bus, sources)]
        source_supervisor = Supervisor(origin)
        source_supervisor.start()
        log.info("job on %s: %s", bus.keys.prefix, ", ".join(f"{n} ({spec.nodes[n].kind})" for n in spec.nodes))
        while not stop.is_set() and source_supervisor.step():
            supervisor.step()
            stop.wait(0.05)
        codes = source_supervisor.exit_codes()
        source_supervisor.stop()
        if not stop.is_set():
            _drain(session, bus, {n for n in downstream if spec.nodes[n].kind not in SINKS})
        return 0 if stop.is_set() or all(codes.get(name) == 0 for name in sources) else 1
    finally:
        if watch is not None:
            watch.gather()
        supervisor.stop()
        if watch is not None:
            watch.close()
        session.close()


def _watch(session, bus: BusConfig, spec: PipelineSpec, display: Display | None) -> JobWatch | None:
    """Progress and summary of the job, when a display is given and it shows either."""
    if display is None or not (display.progress or display.summary):
        return None
    return JobWatch(session, bus, spec, display)


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
