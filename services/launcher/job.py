"""``artrack run``: one job = a source + a tracker's nodes + the sinks asked (recorder, viewer, Foxglove file).

The job is a ``PipelineSpec`` like any pipeline file (``--save-pipeline`` writes it, ``artrack
up`` runs it as a daemon): ``build_job`` fills a tracker template for the source's cameras.
The source is a capture node (any capture URI) or a replay node (``recording:PATH.mcap``:
the cameras' images, calibration and ground truth, restamped as they go out (in a lossless run on the
recording's clock from the first frame's, ``services.runtime.stamps``), on its own
rig or the one asked for). A job differs from a daemon only in its order and its end: the
nodes that read the bus start first; once every one of them is live (plus a moment for their
subscriptions to reach the bus), the sources (the nodes that read nothing). A finite source ends
with an end of stream naming its last frame, and each node publishes its own end once it has
dealt with every frame up to it (``services.runtime.flow``): the job waits for the end of every
node, however long one frame takes, then stops them all, so the recorder closes its file with
everything in it. A node that fails meanwhile ends the wait with its reason. A live source runs
until SIGINT/SIGTERM. How frames flow (lossless or real-time) is the pipeline's ``[flow]``.

A node that exits before it is live ends the job at once, with the last line it wrote
(``JobExit.CANNOT_START``); once up, a node that dies is restarted within the pipeline's
restart budget, and one that spends it ends the job (``JobExit.NODE_FAILED``). While it
runs, the job answers ``PipelineHealth`` as ``artrack up`` does, so ``artrack status``
sees it.
"""

from __future__ import annotations

import logging
import os
import signal
import threading
import time
from dataclasses import dataclass, replace
from enum import IntEnum
from pathlib import Path
from typing import Any

import zenoh

from protocol.codec import encode
from services.bus.discovery import node_reports
from services.bus.session import BusConfig, close_session, open_session
from services.launcher.flags import Flag
from services.launcher.flow import finite
from services.launcher.health import pipeline_health
from services.launcher.pipeline import NodeSpec, PipelineSpec, preflight, processes, resolved
from services.launcher.progress import Display, JobWatch
from services.launcher.supervisor import ChildHealth, Supervisor
from services.launcher.tracker import Tracker
from services.recorder.info import summarise
from services.recorder.reading import EXIT_DAMAGED, NotMcap
from services.runtime.flow import Ends
from services.runtime.memory import settle_heap

log = logging.getLogger(__name__)

SETTLE_S = 0.5
START_LIMIT_S = 30.0
RECORDING_SCHEME = "recording:"
REPLAYED_STREAMS = ("image", "camera_info", "truth")

@dataclass(frozen=True)
class Recording:
    """A recorded session as a job's source: its cameras and the rig it is replayed on (the one it was
    recorded on, unless ``moved_to`` another, where its keys are retargeted).

    A job replays it ``onto`` the namespace and rig of its bus settings: ``where()`` (its own) unless the
    command line or the environment name others."""

    path: Path
    cameras: tuple[str, ...]
    namespace: str
    rig: str
    retarget: bool = False

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

    def where(self) -> dict[str, Any]:
        """The namespace and rig it is replayed on, as bus settings (a pipeline's ``[bus]``)."""
        return {"namespace": self.namespace, "rig": self.rig}

    def moved_to(self, bus: BusConfig) -> Recording:
        """This recording replayed on ``bus``'s namespace and rig instead of its own."""
        return replace(self, namespace=bus.namespace, rig=bus.rig, retarget=True)

    def onto(self, bus: BusConfig) -> Recording:
        """This recording replayed on ``bus``'s namespace and rig: as recorded when they are its own, else
        ``moved_to`` them."""
        return self if (bus.namespace, bus.rig) == (self.namespace, self.rig) else self.moved_to(bus)

    def node(self) -> tuple[str, dict[str, Any]]:
        keys = [f"{camera}/{stream}" for camera in self.cameras for stream in REPLAYED_STREAMS]
        return "replay", {"path": str(self.path), "keys": keys, "restamp": True,
                          **({"retarget": True} if self.retarget else {})}


@dataclass(frozen=True)
class JobFile:
    """A file a job's sink writes as it runs (``artrack run --rerun``, ``--record-foxglove``), overwritten if it
    exists only when ``force``."""

    path: Path
    force: bool = False


class JobExit(IntEnum):
    """How a job ends: its process's exit code (documented in docs/configuration.md, "Exit codes")."""

    DONE = 0
    """every source ended cleanly (or a source that runs until stopped was stopped)"""
    NODE_FAILED = 1
    """a node failed while running: its restart budget is spent, or a source crashed"""
    CANNOT_START = 2
    """a bad option, or a node or source that could not start"""
    DAMAGED_SOURCE = EXIT_DAMAGED
    """the source is a damaged recording: played up to the damage"""
    FRAMES_LOST = 4
    """with ``--strict``: the run ended, but some node dropped or never received a frame"""
    INTERRUPTED = 130
    """SIGINT or SIGTERM before a finite source ended"""


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
              record: Path | None = None, rerun: JobFile | None = None,
              foxglove: JobFile | None = None) -> PipelineSpec:
    """The job's pipeline: the source, the tracker's nodes for its cameras, a recorder, a viewer and a Foxglove
    node writing a file (and serving nothing) if asked; every node validated, its inputs and outputs filled in.
    A tracker's node that does not validate for the source's cameras is first put down to the source, when the
    source cannot start (its check's PipelineError)."""
    name, node = source_node(source)
    where = f"tracker {tracker.name}"
    alone = resolved(PipelineSpec(nodes={name: node}), where)
    cameras = cameras_of(alone.nodes[name])
    placed = node if tracker.source_process is None else node.model_copy(update={"process": tracker.source_process})
    try:
        nodes = {name: placed, **tracker.expand(cameras, options, flags)}
    except ValueError:
        preflight(alone, "job")  # a source that cannot start (a missing folder) is what is wrong, not its cameras
        raise
    if record is not None:
        nodes["recorder"] = NodeSpec(kind="recorder", out=str(record))
    if rerun is not None:
        nodes["viewer"] = NodeSpec(kind="viewer", rrd=str(rerun.path), **({"force": True} if rerun.force else {}))
    if foxglove is not None:
        nodes["foxglove"] = NodeSpec(kind="foxglove", serve=False, mcap=str(foxglove.path),
                                     **({"force": True} if foxglove.force else {}))
    bus = source.where() if isinstance(source, Recording) else {}
    return resolved(PipelineSpec(bus=bus, nodes=nodes), where)


def run_job(bus: BusConfig, spec: PipelineSpec, title: str = "run", display: Display | None = None,
            strict: bool = False) -> int:
    """Run the job to the end of its sources (or a signal); the exit code is a ``JobExit``.

    ``title`` names the job in its ``PipelineHealth`` (``artrack status``). With ``display``, progress
    and a summary go where it says (``services.launcher.progress``), once every node has come up.
    With ``strict``, a run in which any frame was dropped or went missing exits ``FRAMES_LOST``."""
    sources = spec.sources()
    if not sources:
        raise JobError("this pipeline has no source (a node that reads nothing): nothing would ever start it")
    preflight(spec, "job")
    groups = spec.groups()
    feeding = [process for process, names in groups.items() if any(name in sources for name in names)]
    reading = [process for process in groups if process not in feeding]
    downstream = [name for process in reading for name in groups[process]]
    plans = spec.flow_plans()
    ending = {name for name in spec.nodes if name not in sources and plans[name].upstream}
    interrupted = JobExit.DONE if not all(finite(spec.nodes[n].kind, spec.nodes[n].params) for n in sources) \
        else JobExit.INTERRUPTED
    stop = threading.Event()
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda *_: stop.set())
    session = open_session(bus)
    restarting = processes(spec, bus, reading)
    supervisor = Supervisor([replace(p, restart=False) for p in restarting], spec.supervisor)
    source_supervisor = Supervisor([replace(p, restart=False) for p in processes(spec, bus, feeding)],
                                   spec.supervisor)
    supervising = [supervisor]
    health = _answer_health(session, bus, title, spec, supervising)
    ends = Ends(session, bus.keys, ending)
    why: str | None = None  # said last, once every node has stopped
    watch: JobWatch | None = None
    try:
        supervisor.start()
        why = _come_up(session, bus, spec, supervisor, set(downstream), stop)
        if why is None:
            time.sleep(SETTLE_S)  # a node may fail just after it went live (say, on opening its output)
            why = _exited(spec, supervisor)
        if why is not None:
            return JobExit.CANNOT_START
        if stop.is_set():
            return interrupted
        for process in restarting:  # up: from now on a node that dies is restarted, within the budget
            supervisor.update(process)
        settle_heap()  # this process may be a client too (the demo's): no full collection of its start-up mid-run
        watch = _watch(session, bus, spec, display, strict)
        source_supervisor.start()
        supervising.append(source_supervisor)
        log.info("job on %s: %s", bus.keys.prefix, ", ".join(f"{n} ({spec.nodes[n].kind})" for n in spec.nodes))
        while not stop.is_set() and source_supervisor.step():
            supervisor.step()
            if (why := _failed(spec, supervisor)) is not None:
                return JobExit.NODE_FAILED
            stop.wait(0.05)
        if stop.is_set():
            return interrupted
        ended, why = _sources_ended(source_supervisor.health())
        if ended == JobExit.DONE:
            why = _await_ends(spec, ends, supervisor, stop)
            if why is not None:
                return JobExit.NODE_FAILED
            if stop.is_set():
                return interrupted
        if watch is not None:
            watch.restarts = {child.name: child.restarts for child in supervisor.health() if child.restarts}
        if strict and ended == JobExit.DONE and watch is not None:
            watch.gather()
            why = watch.losses()
            if why is not None:
                return JobExit.FRAMES_LOST
        return ended
    finally:
        ends.close()
        source_supervisor.stop()
        if watch is not None:
            watch.gather()
        supervisor.stop()
        health.undeclare()
        if watch is not None:
            watch.close()
        close_session(session)
        if why is not None:
            log.error("%s", why)


def _answer_health(session: zenoh.Session, bus: BusConfig, title: str, spec: PipelineSpec,
                   supervising: list[Supervisor]) -> zenoh.Queryable:
    """Answer ``PipelineHealth`` for the nodes of the started ``supervising``, as ``artrack up`` does."""
    key = bus.keys.supervisor(f"run-{os.getpid()}")
    started = time.monotonic()

    def answer(query: zenoh.Query) -> None:
        children = [child for each in list(supervising) for child in each.health()]
        query.reply(key, encode(pipeline_health(title, spec, children, time.monotonic() - started)))

    return session.declare_queryable(key, answer)


def _come_up(session: zenoh.Session, bus: BusConfig, spec: PipelineSpec, supervisor: Supervisor, names: set[str],
             stop: threading.Event) -> str | None:
    """Wait until every node of ``names`` is live (or ``stop``): None; else why one cannot start, in one line
    (the first process that exited, with the last line it wrote)."""
    deadline = time.monotonic() + START_LIMIT_S
    while not stop.is_set():
        if (why := _exited(spec, supervisor)) is not None:
            return why
        live = _ours_live(session, bus, spec, supervisor, names)
        if live == names:
            return None
        if time.monotonic() > deadline:
            return f"nodes {sorted(names - live)} did not come up within {START_LIMIT_S:.0f} s"
    return None


def _process(spec: PipelineSpec, process: str) -> str:
    """How a message names a process of ``spec``: ``node NAME`` for a lone node's, else ``process NAME (nodes)``."""
    names = spec.groups()[process]
    return f"node {process}" if names == (process,) else f"process {process} ({', '.join(names)})"


def _exited(spec: PipelineSpec, supervisor: Supervisor) -> str | None:
    """Why the first of the supervisor's processes that exited could not start, in one line (None while none has)."""
    supervisor.step()
    ended = next((child for child in supervisor.health() if child.exit_code is not None), None)
    return None if ended is None else \
        f"{_process(spec, ended.name)} could not start: {ended.reason.removeprefix(f'node {ended.name}: ')}"


def _ours_live(session: zenoh.Session, bus: BusConfig, spec: PipelineSpec, supervisor: Supervisor,
               names: set[str]) -> set[str]:
    """The nodes of ``names`` that answer on this rig from the very processes ``supervisor`` started: a node
    of the same name that another pipeline runs here is not this job's node coming up."""
    pids = {child.name: child.pid for child in supervisor.health()}
    return {name for (rig, name), stats in node_reports(session, bus.keys, 0.3)
            if rig == bus.rig and name in names and stats.pid == pids.get(spec.process_of(name))}


def _failed(spec: PipelineSpec, supervisor: Supervisor) -> str | None:
    """Why a process the supervisor gave up on failed (None while none has)."""
    failed = next((child.name for child in supervisor.health() if child.state == "failed"), None)
    return None if failed is None else f"{_process(spec, failed)} failed: {supervisor.failure(failed)}"


def _sources_ended(children: list[ChildHealth]) -> tuple[JobExit, str | None]:
    """The job's exit once its sources all ended, and why when not DONE (the sources that did not exit 0)."""
    codes = {child.exit_code for child in children}
    why = "; ".join(f"source {child.name} ended with code {child.exit_code}: {child.reason}"
                    for child in children if child.exit_code != 0) or None
    if codes == {0}:
        return JobExit.DONE, None
    if JobExit.CANNOT_START in codes:
        return JobExit.CANNOT_START, why
    damaged = codes <= {0, EXIT_DAMAGED}
    return (JobExit.DAMAGED_SOURCE, why) if damaged else (JobExit.NODE_FAILED, why)


def _watch(session, bus: BusConfig, spec: PipelineSpec, display: Display | None, strict: bool) -> JobWatch | None:
    """Progress and summary of the job, when a display is given and it shows either; figures alone for
    ``strict`` (it judges the run by them)."""
    shows = display is not None and (display.progress or display.summary)
    if not shows and not strict:
        return None
    return JobWatch(session, bus, spec, display if shows and display is not None else Display(summary=False))


def _await_ends(spec: PipelineSpec, ends: Ends, supervisor: Supervisor, stop: threading.Event) -> str | None:
    """Wait until every node ``ends`` waits for has ended, or ``stop``: None; else why a process failed first.
    A node whose process finished (exited 0) without its end is not waited for."""
    groups = spec.groups()
    asked = time.monotonic()
    while not stop.is_set():
        supervisor.step()
        if (why := _failed(spec, supervisor)) is not None:
            return why
        finished = {name for child in supervisor.health() if child.state == "finished" for name in groups[child.name]}
        if not ends.waiting() - finished:
            return None
        if time.monotonic() - asked >= 2.0:
            ends.ask()
            asked = time.monotonic()
        stop.wait(0.05)
    return None
