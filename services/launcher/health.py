"""A pipeline's ``PipelineHealth``: what ``artrack up`` and ``artrack run`` answer ``artrack status`` with."""

from __future__ import annotations

import os
import socket
import time
from collections.abc import Iterable

from protocol.message import Header
from protocol.system import PipelineHealth, SupervisedNode
from services.launcher.pipeline import PipelineSpec
from services.launcher.supervisor import ChildHealth


def pipeline_health(pipeline: str, spec: PipelineSpec, children: Iterable[ChildHealth],
                    uptime_s: float) -> PipelineHealth:
    """This process's answer for ``pipeline`` (a file, or what the job runs): every node of ``spec`` in the
    supervised processes ``children`` (the nodes of a process group share its process's health)."""
    groups = spec.groups()
    nodes = tuple(SupervisedNode(name=name, kind=spec.nodes[name].kind, state=h.state, pid=h.pid,
                                 uptime_s=h.uptime_s, restarts=h.restarts, exit_code=h.exit_code)
                  for h in children for name in groups[h.name])
    return PipelineHealth(header=Header(stamp_ns=time.time_ns()), pipeline=pipeline, host=socket.gethostname(),
                          pid=os.getpid(), uptime_s=uptime_s, nodes=nodes)
