"""Several nodes in one process: a process group.

Each member stays a node of its own (its name, liveliness token, stats, end of stream, live
parameters, logs) and runs its body on a thread of its own; the members share the process's
``Host``, so a message from one to another passes as the Python object (``services.bus.local``)
and goes onto the bus, encoded once, only while another session subscribes to its key.

The members that read the bus are made and started first (a name another process holds is refused
on theirs before any source exists); the sources (members that read nothing) start once
every other member waits for its inputs (``Node.serving``) and ``SETTLE_S`` more has passed, so no
frame goes out before its consumers in the process can take it. Once the sources have returned
and every other member has published its end of stream, the process stops them and exits, as a
lone source's process exits at its end. SIGINT and SIGTERM stop every member. A member that fails
(code 1 or 2) stops the others, and the process exits with the worst code: 2 (``EXIT_CANNOT_RUN``) when one
cannot do its job, else 1 when one failed, else the highest code a body returned (a replay's 3).
A supervisor restarts the process, the whole group, as it restarts a lone node.
"""

from __future__ import annotations

import logging
import signal
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from services.bus.session import BusConfig, BusError
from services.runtime.flow import FlowPlan
from services.runtime.host import Host
from services.runtime.memory import settle_heap
from services.runtime.node import NameTaken, Node, Stopper, serve
from services.runtime.restarts import EXIT_CANNOT_RUN

log = logging.getLogger("artrack.group")

SERVING_WAIT_S = 10.0
"""How long sources wait for the other members to serve before starting anyway (one slow to start)."""
SETTLE_S = 0.5
"""How long sources wait once the other members serve, as a job waits between its nodes coming up and its
sources starting: what a node starts beside its loop (the SLAM node's mapping process) gets under way."""
POLL_S = 0.1


@dataclass(frozen=True)
class Member:
    """One node of a group: its name, kind, body, part in the flow, and whether it is a source."""

    name: str
    kind: str
    body: Callable[[Node], object]
    flow: FlowPlan
    source: bool = False


class _Thread(threading.Thread):
    """A member's body on a thread of its own; ``code`` is its exit code once it has ended."""

    def __init__(self, member: Member, node: Node):
        super().__init__(name=member.name, daemon=True)
        self.member = member
        self.node = node
        self.code: int | None = None

    def run(self) -> None:
        self.code = serve(self.node, self.member.body)


def worst(codes: Sequence[int]) -> int:
    """The group's exit code from its members': 2 first, then 1, then the highest other."""
    for code in (EXIT_CANNOT_RUN, 1):
        if code in codes:
            return code
    return max(codes, default=0)


def run_group(group: str, bus: BusConfig, members: Sequence[Member]) -> int:
    """Run ``members`` in this process as group ``group`` until every body has returned (or a signal,
    or a member's failure); the group's exit code (``worst``)."""
    try:
        host = Host(bus)
    except BusError as exc:
        log.error("%s", exc)
        return EXIT_CANNOT_RUN
    members = sorted(members, key=lambda member: member.source)  # as they start: a refused name is a consumer's
    stopper = Stopper()
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, stopper)
    nodes: list[Node] = []
    try:
        for member in members:
            nodes.append(Node(member.name, member.kind, bus, flow=member.flow, host=host))
            stopper.add(nodes[-1])
    except (BusError, NameTaken) as exc:
        log.error("%s", exc)
        for node in nodes:
            node.close()
        host.close()
        return EXIT_CANNOT_RUN
    log.info("process %s: %s", group, ", ".join(f"{m.name} ({m.kind})" for m in members))
    settle_heap()
    threads = [_Thread(member, node) for member, node in zip(members, nodes, strict=True)]
    try:
        _start(threads, stopper.asked)
        while any(thread.is_alive() for thread in threads):
            for thread in threads:
                thread.join(POLL_S)
                if thread.code in (1, EXIT_CANNOT_RUN) and not stopper.asked.is_set():
                    log.warning("process %s: node %s ended with code %d, stopping the others", group,
                                thread.member.name, thread.code)
                    stopper()
            if not stopper.asked.is_set() and _done(threads):
                stopper()
    finally:
        for node in nodes:
            node.close()
        host.close()
    failure = next((node.failure for node in nodes if node.failure), None)
    if failure is not None:
        log.error("%s", failure)  # the last line, the reason a supervisor gives for the process's exit
    return worst([thread.code for thread in threads if thread.code is not None])


def _done(threads: list[_Thread]) -> bool:
    """Whether the group's job is done: it has sources, they have all returned, and every other member has
    published its end of stream (one that waits for no upstream end would never end by itself)."""
    sources = [thread for thread in threads if thread.member.source]
    return bool(sources) and not any(thread.is_alive() for thread in sources) and all(
        thread.node.ended or not thread.node.flow.upstream for thread in threads if not thread.member.source)


def _start(threads: list[_Thread], stopping: threading.Event) -> None:
    """Start the members that read the bus, then, once each serves (or has ended), the sources."""
    consumers = [thread for thread in threads if not thread.member.source]
    for thread in consumers:
        thread.start()
    deadline = time.monotonic() + SERVING_WAIT_S
    for thread in consumers:
        while not (thread.node.serving.is_set() or not thread.is_alive() or stopping.is_set()):
            if time.monotonic() > deadline:
                log.warning("node %s is not serving after %.0f s; starting the sources anyway", thread.member.name,
                            SERVING_WAIT_S)
                break
            thread.node.serving.wait(POLL_S)
    if consumers:
        stopping.wait(SETTLE_S)
    for thread in threads:
        if thread.member.source:
            thread.start()
