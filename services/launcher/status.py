"""``artrack status``: the health of a rig in one look.

It gathers, from one bus session: every ``artrack up`` or ``artrack run`` process's ``PipelineHealth``
(supervised nodes: state, pid, uptime, restarts), every node's ``NodeStats`` (rates, drops,
messages of synced inputs that joined no set, decode errors, processing p50/p99, latency
p50/p99: an input's age when the node was done with it), and every client app's
``ClientState`` with its subscriptions. A subscription that matches no key a live node
publishes (its output streams in ``NodeStats.streams``) is flagged: the app waits for
something nobody sends.

``--check`` is the health-check contract (docker HEALTHCHECK, systemd): healthy, exit 0,
only when at least one ``artrack up`` or ``artrack run`` answered and every node it supervises is
running.
``--here`` keeps only the ``artrack up`` processes of this host, so each container of a
deployment checks its own nodes rather than the whole rig's.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import zenoh

from protocol.keys import Keys
from protocol.system import ClientState, NodeStats, PipelineHealth
from services.bus.discovery import client_states, first_answers, node_states
from services.launcher.observe import format_table

HEALTHY, UNHEALTHY = 0, 1


@dataclass
class Status:
    """What answered: supervisors by pipeline key, node stats and client states by name (this rig)."""

    pipelines: dict[str, PipelineHealth] = field(default_factory=dict)
    nodes: dict[str, NodeStats] = field(default_factory=dict)
    clients: dict[str, ClientState] = field(default_factory=dict)

    def published(self) -> set[str]:
        """Keys some live node publishes."""
        return {s.key for stats in self.nodes.values() for s in stats.streams if s.direction == "out"}

    def unmatched(self) -> list[tuple[str, str]]:
        """``(app, key expression)`` of every client subscription no published key matches."""
        published = [zenoh.KeyExpr(key) for key in self.published()]
        return [(state.app, sub.key) for state in self.clients.values() for sub in state.subscriptions
                if not any(zenoh.KeyExpr(sub.key).intersects(key) for key in published)]

    def problems(self) -> list[str]:
        """Why the rig is not healthy (empty when it is): see the module docstring."""
        if not self.pipelines:
            return ["no `artrack up` or `artrack run` answered on this rig"]
        return [f"node {n.name} is {n.state.replace('_', ' ')}" for health in self.pipelines.values()
                for n in health.nodes if n.state != "running"]

    def to_json(self) -> dict:
        """A JSON-ready summary: per pipeline its nodes (supervision merged with stats), clients, problems."""
        return {
            "pipelines": [{
                "pipeline": health.pipeline, "host": health.host, "pid": health.pid, "uptime_s": health.uptime_s,
                "nodes": [{**node.model_dump(mode="json"), "stats": _stats_json(self.nodes.get(node.name))}
                          for node in health.nodes],
            } for health in self.pipelines.values()],
            "unsupervised": [_stats_json(stats) for name, stats in sorted(self.nodes.items())
                             if name not in self.supervised()],
            "clients": [{"app": c.app, "client": c.client, "host": c.host, "pid": c.pid,
                         "subscriptions": [s.model_dump(mode="json") for s in c.subscriptions]}
                        for c in self.clients.values()],
            "warnings": self.warnings(),
            "problems": self.problems(),
            "healthy": not self.problems(),
        }

    def on_host(self, host: str) -> Status:
        """Only the pipelines supervised on ``host`` (a container's health check looks at its own)."""
        return Status({key: health for key, health in self.pipelines.items() if health.host == host},
                      self.nodes, self.clients)

    def warnings(self) -> list[str]:
        return [f"app {app} waits for {key} but no node publishes it" for app, key in self.unmatched()]

    def supervised(self) -> set[str]:
        return {n.name for health in self.pipelines.values() for n in health.nodes}


def _stats_json(stats: NodeStats | None) -> dict | None:
    if stats is None:
        return None
    return {"node": stats.node, "kind": stats.kind, "pid": stats.pid, "state": stats.state,
            "uptime_s": stats.uptime_s, "in_hz": _rate(stats, "in"), "out_hz": _rate(stats, "out"),
            "received": stats.received, "processed": stats.processed, "published": stats.published,
            "dropped": stats.dropped, "missing": stats.missing, "ended": stats.ended,
            "unjoined": stats.unjoined, "decode_errors": stats.decode_errors,
            "inputs": [{"key": s.key, "received": s.messages, "dropped": s.dropped, "missing": s.missing}
                       for s in stats.streams if s.direction == "in"],
            "processing_ms_p50": stats.processing_ms_p50, "processing_ms_p99": stats.processing_ms_p99,
            "latency_ms_p50": stats.latency_ms_p50, "latency_ms_p99": stats.latency_ms_p99}


def _rate(stats: NodeStats, direction: str) -> float:
    return sum(s.rate_hz for s in stats.streams if s.direction == direction)


def gather(session: zenoh.Session, keys: Keys, timeout_s: float) -> Status:
    """Ask the rig's supervisors, nodes and client apps (each waits up to ``timeout_s``)."""
    pipelines = first_answers(session, keys.supervisors(), PipelineHealth, timeout_s)
    nodes = {name: s for (rig, name), s in node_states(session, keys, timeout_s).items() if rig == keys.rig}
    clients = {cid: c for (rig, cid), c in client_states(session, keys, timeout_s).items() if rig == keys.rig}
    return Status(pipelines, nodes, clients)


def _cell(value: float | None, digits: int = 1) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def format_status(status: Status) -> str:
    """Tables of the nodes (supervised first; IN/s and OUT/s summed over each node's keys; IN, DONE,
    DROPPED and MISSING: frames received, processed, dropped by the node and never received), of each
    node's inputs (received, dropped, missing), and of client apps, then warnings and problems."""
    header = ("PIPELINE", "NODE", "KIND", "STATE", "PID", "UP(s)", "RESTARTS", "IN/s", "OUT/s", "IN", "DONE",
              "DROPPED", "MISSING", "UNJOINED", "DECODE_ERR", "P50(ms)", "P99(ms)", "LAT50(ms)", "LAT99(ms)")
    rows: list[tuple[str, ...]] = [header]
    for health in status.pipelines.values():
        for node in health.nodes:
            rows.append((Path(health.pipeline).name, node.name, node.kind, node.state, str(node.pid or "-"),
                         f"{node.uptime_s:.0f}", str(node.restarts), *_figures(status.nodes.get(node.name))))
    for name, stats in sorted(status.nodes.items()):
        if name not in status.supervised():
            rows.append(("-", name, stats.kind, stats.state, str(stats.pid), f"{stats.uptime_s:.0f}", "-",
                         *_figures(stats)))
    lines = [format_table(rows)]
    inputs: list[tuple[str, ...]] = [("NODE", "INPUT", "RECEIVED", "DROPPED", "MISSING")]
    for name, stats in sorted(status.nodes.items()):
        inputs += [(name, s.key, str(s.messages), str(s.dropped), str(s.missing))
                   for s in stats.streams if s.direction == "in"]
    if len(inputs) > 1:
        lines += ["", format_table(inputs)]
    if status.clients:
        clients: list[tuple[str, ...]] = [("APP", "CLIENT", "HOST", "PID", "SUBSCRIPTION", "RECEIVED")]
        for c in status.clients.values():
            for sub in c.subscriptions or ():
                clients.append((c.app, c.client, c.host, str(c.pid), sub.key, str(sub.received)))
            if not c.subscriptions:
                clients.append((c.app, c.client, c.host, str(c.pid), "-", "-"))
        lines += ["", format_table(clients)]
    lines += [f"warning: {w}" for w in status.warnings()]
    lines += [f"unhealthy: {p}" for p in status.problems()]
    return "\n".join(lines)


def _figures(stats: NodeStats | None) -> tuple[str, ...]:
    if stats is None:
        return ("-",) * 12
    return (_cell(_rate(stats, "in")), _cell(_rate(stats, "out")), str(stats.received), str(stats.processed),
            str(stats.dropped), str(stats.missing), str(stats.unjoined), str(stats.decode_errors),
            _cell(stats.processing_ms_p50, 2), _cell(stats.processing_ms_p99, 2),
            _cell(stats.latency_ms_p50, 2), _cell(stats.latency_ms_p99, 2))
