"""``artrack up``: a pipeline file run as supervised processes, for days.

The process supervises one process per node (``services.launcher.supervisor``: back-off and
restart budget from the file's ``[supervisor]`` table), answers ``PipelineHealth`` on
``keys.supervisor(<file stem>)`` (what ``artrack status`` reads), and on SIGHUP re-reads
the file: reloadable parameter changes are pushed to the running nodes through their
config queryables, anything else refuses the reload with reasons naming node and field,
and the running pipeline stays as it was (``services.runtime.reconfig``).
"""

from __future__ import annotations

import logging
import re
import threading
import time
from pathlib import Path

import zenoh

from protocol.codec import encode
from protocol.system import PipelineHealth
from services.bus.session import BusConfig, BusError, close_session, open_session
from services.launcher.health import pipeline_health
from services.launcher.pipeline import PipelineError, PipelineSpec, params_model, processes, read_pipeline
from services.launcher.reload import plan_reload, request_change
from services.launcher.supervisor import Supervisor

log = logging.getLogger("artrack.up")

ANSWER_TIMEOUT_S = 2.0
JOIN_S = 10.0
"""How long stopping waits for the thread that opens this process's session to leave Zenoh."""


def pipeline_name(path: Path) -> str:
    """The name a pipeline file's health is answered under: its stem, other characters as ``_``."""
    return re.sub(r"[^A-Za-z0-9_.\-]", "_", path.stem) or "pipeline"


class Daemon:
    """One running pipeline: its supervisor, health queryable and reload (see the module docstring)."""

    def __init__(self, path: Path, spec: PipelineSpec, bus: BusConfig):
        self.path = path
        self.spec = spec
        self.bus = bus
        self.name = pipeline_name(path)
        self.supervisor = Supervisor(processes(spec, bus), spec.supervisor)
        self._started = time.monotonic()
        self._lock = threading.Lock()
        self._left = False
        self.session: zenoh.Session | None = None
        self._queryable: zenoh.Queryable | None = None

    def health(self) -> PipelineHealth:
        """Every supervised node's state now."""
        return pipeline_health(str(self.path), self.spec, self.supervisor.health(), time.monotonic() - self._started)

    def _on_health(self, query: zenoh.Query) -> None:
        query.reply(self.bus.keys.supervisor(self.name), encode(self.health()))

    def _join(self) -> None:
        """Open this process's session and answer health on it. Runs beside the supervisor: with
        ``retry`` a router that is not there yet is waited for while the nodes are already started."""
        try:
            session = open_session(self.bus)
        except BusError as exc:
            log.error("%s; the nodes run, but `artrack status` cannot see this pipeline", exc)
            return
        with self._lock:
            if self._left:
                close_session(session)
                return
            self.session = session
            self._queryable = session.declare_queryable(self.bus.keys.supervisor(self.name), self._on_health)

    def _leave(self) -> None:
        with self._lock:
            self._left = True
            if self._queryable is not None:
                self._queryable.undeclare()
            if self.session is not None:
                close_session(self.session)

    def reload(self) -> bool:
        """Re-read the file and apply its live changes; False (everything logged) when refused."""
        if self.session is None:
            log.error("reload refused: %s is not on the bus yet, so its nodes cannot be reached", self.path)
            return False
        try:
            wanted = read_pipeline(self.path)
        except PipelineError as exc:
            log.error("reload refused: %s", exc)
            return False
        plan = plan_reload(self.spec, wanted, params_model)
        if plan.refused:
            for reason in plan.refused:
                log.error("reload refused: %s", reason, extra={"pipeline": str(self.path)})
            log.error("reload of %s refused: the running pipeline is unchanged", self.path)
            return False
        if not plan.changes:
            log.info("reload of %s: nothing changed", self.path)
            return True
        nodes = dict(self.spec.nodes)
        restarts = {spec.name: spec for spec in processes(wanted, self.bus)}
        for name, values in sorted(plan.changes.items()):
            answer = request_change(self.session, self.bus.keys, name, values, ANSWER_TIMEOUT_S)
            if answer is not None and answer.refused:
                log.error("reload: node %s refused %s", name, answer.refused, extra={"node_name": name})
                continue
            if answer is None:
                log.warning("reload: node %s did not answer; its next start uses %s", name, values)
            else:
                log.info("reload: node %s applied %s", name, answer.applied, extra={"node_name": name})
            nodes[name] = wanted.nodes[name]
            self.supervisor.update(restarts[wanted.process_of(name)])
        self.spec = self.spec.model_copy(update={"nodes": nodes})
        return True

    def run(self, stop: threading.Event, hup: threading.Event) -> int:
        """Supervise until ``stop`` (or until every node finished or failed), reloading on ``hup``.

        Exit code 1 when a node ended failed, else 0.
        """
        reloader = threading.Thread(target=self._reloads, args=(stop, hup), name="reload", daemon=True)
        joiner = threading.Thread(target=self._join, name="bus", daemon=True)
        log.info("pipeline %s: %d node(s) on %s", self.path, len(self.spec.nodes), self.bus.keys.prefix)
        self.supervisor.start()
        joiner.start()
        reloader.start()
        try:
            self.supervisor.run(stop)
        finally:
            stop.set()
            reloader.join()
            self._leave()
            joiner.join(JOIN_S)  # a thread still inside Zenoh as Python shuts down would abort the process
        failed = [h.name for h in self.supervisor.health() if h.state == "failed"]
        log.info("pipeline %s stopped%s", self.path, f"; failed: {', '.join(failed)}" if failed else "")
        return 1 if failed else 0

    def _reloads(self, stop: threading.Event, hup: threading.Event) -> None:
        while not stop.is_set():
            if hup.wait(0.1):
                hup.clear()
                log.info("SIGHUP: re-reading %s", self.path)
                self.reload()
