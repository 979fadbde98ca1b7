"""A live pipeline benchmark's bus: a private router, the nodes and source as processes, this process as a
client app timing every pose.

``LiveBus`` (a context manager) opens an in-process router on a free loopback port, a fresh rig, this
process's session and a client app (``services.client``) following every pose of the rig; ``nodes``
starts node processes and waits until each answers, ``source`` starts ``tests.bench.frame_source``,
``follow`` waits until the source is done and the poses have stopped coming. ``latencies`` gives, per
frame, the arrival here of its last pose - the frame's stamp; ``stats`` the nodes' own ``NodeStats``.
Leaving the context stops every process it started (killed after 5 s) and closes the client, the
session and the router, whatever happened before.

This process keeps every pose it is sent (tens of thousands of objects in a minute at 240 Hz), so its
garbage collector's full passes would grow to tens of milliseconds (44 and 94 ms in one 20 s stereo run):
arrivals held up for as long, counted as the pipeline's latency, and a core taken from the pipeline's
processes meanwhile. Inside the context the heap it started with is frozen and automatic collection is off
(``gc.freeze``, ``gc.disable``), as a real-time app that keeps its history would arrange; leaving turns it
back on.
"""

from __future__ import annotations

import gc
import json
import os
import subprocess
import sys
import time
import uuid
from pathlib import Path
from typing import Any

import zenoh

from protocol.system import NodeStats
from services.bus.discovery import node_states
from services.bus.session import BusConfig, open_session
from services.client import PoseUpdate, connect
from services.launcher.observe import wait_for_nodes
from services.launcher.pipeline import node_command
from services.launcher.router import router_config
from tests.bench.frame_source import RENDERED, source_argv
from tests.bench.link import free_port, stop_processes

ROOT = Path(__file__).resolve().parents[2]
START_S = 30.0
QUIET_S = 2.0


class LiveBus:
    """A private bus for one pipeline run; ``app`` names this process's client app."""

    def __init__(self, app: str):
        self.app = app
        self.arrived: list[PoseUpdate] = []
        self.processes: list[subprocess.Popen] = []

    def __enter__(self) -> LiveBus:
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        self.router = zenoh.open(router_config((self.endpoint,), (), None))
        self.bus = BusConfig(connect=(self.endpoint,), rig=f"bench{uuid.uuid4().hex[:6]}", autostart_router=False)
        self.env = {**os.environ, **self.bus.to_env()}
        self.session = open_session(self.bus)
        self.client = connect(connect=self.endpoint, namespace=self.bus.namespace, rig=self.bus.rig, app=self.app)
        self.client.on_pose("**", self.arrived.append)
        gc.collect()
        gc.freeze()
        gc.disable()
        return self

    def __exit__(self, *exc: object) -> None:
        gc.enable()
        try:
            self.client.close()
            stop_processes(self.processes)
        finally:
            self.session.close()
            self.router.close()

    def start(self, argv: list[str], **popen: Any) -> subprocess.Popen:
        """A process on this bus (its environment carries the bus settings), stopped on leaving."""
        process = subprocess.Popen(argv, cwd=ROOT, env=self.env, **popen)
        self.processes.append(process)
        return process

    def nodes(self, nodes: dict[str, tuple[str, dict[str, Any]]]) -> list[subprocess.Popen]:
        """``{name: (kind, params)}`` started, each its own process, once all answer; RuntimeError after
        ``START_S``."""
        started = [self.start(node_command(kind, name, params)) for name, (kind, params) in nodes.items()]
        if (up := wait_for_nodes(self.session, self.bus.keys, set(nodes), START_S)) != set(nodes):
            raise RuntimeError(f"nodes {sorted(set(nodes) - up)} did not come up")
        return started

    def source(self, scene: str, rate: float, frames: int, rendered: int = RENDERED,
               **options: Any) -> subprocess.Popen:
        """``tests.bench.frame_source`` publishing ``frames`` instants of ``scene`` (``rendered`` of them
        rendered first, cycled) at ``rate`` Hz; ``options`` are the scene's."""
        argv = source_argv(scene, rate, frames, rendered, **options)
        return self.start([sys.executable, "-m", "tests.bench.frame_source", *argv], stdout=subprocess.PIPE, text=True)

    def follow(self, source: subprocess.Popen) -> dict[str, Any]:
        """Wait until ``source`` has exited and no pose has come for ``QUIET_S``; the source's closing line."""
        quiet_since, seen = time.monotonic(), 0
        while time.monotonic() - quiet_since < QUIET_S or source.poll() is None:
            time.sleep(0.1)
            if len(self.arrived) != seen:
                quiet_since, seen = time.monotonic(), len(self.arrived)
        return json.loads(source.stdout.read() if source.stdout else "{}")

    def latencies(self, warmup: int) -> list[float]:
        """Per frame from seq ``warmup`` on, in seq order: ms from its stamp to the arrival of its last pose."""
        arrivals: dict[int, int] = {}
        stamps: dict[int, int] = {}
        for update in self.arrived:
            seq = update.pose.header.seq
            arrivals[seq] = max(arrivals.get(seq, 0), update.received_ns)
            stamps[seq] = update.pose.header.stamp_ns
        return [(arrivals[seq] - stamps[seq]) / 1e6 for seq in sorted(arrivals) if seq >= warmup]

    def stats(self, names: list[str]) -> dict[str, NodeStats | None]:
        """Each node's own stats as it answers now (None for one that does not)."""
        states = node_states(self.session, self.bus.keys, 2.0)
        return {name: states.get((self.bus.rig, name)) for name in names}

