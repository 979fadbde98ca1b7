"""How the operating system schedules a job's processes: their priority (``nice``) and the CPUs they may run on.

A tracker that shares its machine with other work gets a share of the cores like every other process, and a
real-time pipeline that needs most of a core drops frames as soon as something else runs. A node may ask for
more (or less) in its pipeline table or by flag::

    [nodes.bodies]
    kind = "rigid_bodies"
    nice = -10          # -20 (most urgent) .. 19 (least); default: the launcher's own
    cpus = [1]          # the CPUs it may run on; default: those the launcher may

``artrack run TRACKER --nice [NODE=]N --cpus [NODE=]LIST`` sets the same (without ``NODE=``: every node but
the sinks, whose files are written at their own pace). A process runs its nodes on threads that share the
interpreter, so it takes the most urgent ``nice`` of its nodes; its nodes may not name different ``cpus``.
The supervisor applies both in each process it starts (and restarts) before the process runs any code, so
every thread the process makes inherits them, its mapping or helper processes too.

Lowering a priority needs nothing; raising one above the launcher's (a ``nice`` below its own) needs the
``CAP_SYS_NICE`` capability, or a nice limit (``ulimit -e``, ``LimitNICE=`` of systemd) that allows it. Both
are checked before any process starts: a job that asks for what the machine does not allow is refused in one
line naming the node.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Mapping
from dataclasses import dataclass

NICE_RANGE = (-20, 19)


@dataclass(frozen=True)
class Scheduling:
    """A process's ``nice`` and ``cpus`` (None: as the launcher's)."""

    nice: int | None = None
    cpus: tuple[int, ...] | None = None


def parse_nice(text: str) -> int:
    """``N`` of ``--nice [NODE=]N`` (ValueError saying what to give)."""
    try:
        value = int(text)
    except ValueError:
        raise ValueError(f"give [NODE=]N, N a whole number from {NICE_RANGE[0]} to {NICE_RANGE[1]}") from None
    if not NICE_RANGE[0] <= value <= NICE_RANGE[1]:
        raise ValueError(f"nice must be from {NICE_RANGE[0]} (most urgent) to {NICE_RANGE[1]}, got {value}")
    return value


def parse_cpus(text: str) -> tuple[int, ...]:
    """``LIST`` of ``--cpus [NODE=]LIST``: ``0,2-3`` as ``(0, 2, 3)`` (ValueError saying what to give)."""
    found: list[int] = []
    for part in text.split(","):
        first, sep, last = part.partition("-")
        if not (first.isdigit() and (last.isdigit() and int(last) >= int(first) if sep else True)):
            raise ValueError("give [NODE=]LIST, LIST CPU numbers and ranges such as 0,2-3")
        found += range(int(first), int(last if sep else first) + 1)
    return tuple(sorted(set(found)))


def check_scheduling(asked: Mapping[str, Scheduling]) -> None:
    """ValueError naming the node when one of ``asked`` (node name -> what it asks for) names CPUs this process may
    not run on, or a priority above this process's that it may not give."""
    allowed = sorted(os.sched_getaffinity(0))
    own = os.getpriority(os.PRIO_PROCESS, 0)
    for name, scheduling in asked.items():
        if scheduling.cpus is not None and not set(scheduling.cpus) <= set(allowed):
            raise ValueError(f"nodes.{name}.cpus {list(scheduling.cpus)}: this machine lets artrack run on CPUs "
                             f"{', '.join(map(str, allowed))} only")
        if scheduling.nice is not None and scheduling.nice < own and not may_raise_priority(scheduling.nice):
            raise ValueError(f"nodes.{name}.nice {scheduling.nice}: a priority above this process's (nice {own}) "
                             f"needs the CAP_SYS_NICE capability or a nice limit that allows it (`ulimit -e`, "
                             f"systemd's LimitNICE=); this user has neither: give nice {own} or more")


def may_raise_priority(nice: int) -> bool:
    """Whether this process may give a process ``nice``: tried on a thread of its own that then ends (Linux keeps
    a nice per thread, so the process's other threads keep theirs)."""
    allowed: list[bool] = []

    def probe() -> None:
        try:
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), nice)
        except PermissionError:
            allowed.append(False)
        else:
            allowed.append(True)

    thread = threading.Thread(target=probe, name="nice probe")
    thread.start()
    thread.join()
    return allowed[0]


def apply_scheduling(scheduling: Scheduling) -> None:
    """Give the calling process (its one thread, before it makes any other) ``scheduling``."""
    if scheduling.nice is not None:
        os.setpriority(os.PRIO_PROCESS, 0, scheduling.nice)
    if scheduling.cpus is not None:
        os.sched_setaffinity(0, scheduling.cpus)


__all__ = ["NICE_RANGE", "Scheduling", "apply_scheduling", "check_scheduling", "may_raise_priority", "parse_cpus",
           "parse_nice"]
