"""``artrack status``, ``list``, ``echo`` and ``config``: what runs on the bus, its messages and its live
parameters; ``artrack schemas``: the JSON Schemas of the messages."""

from __future__ import annotations

import argparse
import json
import logging
import signal
import socket
import sys
from pathlib import Path

from services.bus.session import close_session, open_session
from services.cli.bus_options import add_bus_options, bus_config

log = logging.getLogger("artrack")

EXIT_NOTHING = 1
"""Exit status of ``echo`` when nothing arrived before ``--timeout`` (as ``config`` and ``control`` when no node
answers)."""


def cmd_status(args: argparse.Namespace) -> int:
    from services.launcher.status import HEALTHY, UNHEALTHY, format_status, gather

    bus = bus_config(args)
    session = open_session(bus)
    try:
        status = gather(session, bus.keys, args.timeout)
    finally:
        close_session(session)
    if args.here:
        status = status.on_host(socket.gethostname())
    print(json.dumps(status.to_json()) if args.json else format_status(status))
    return (UNHEALTHY if status.problems() else HEALTHY) if args.check else 0


def cmd_config(args: argparse.Namespace) -> int:
    from services.launcher.reload import request_change

    values = {}
    for option in args.set or ():
        name, sep, text = option.partition("=")
        if not sep or not name:
            raise ValueError(f"--set {option!r}: give FIELD=VALUE")
        values[name] = text  # the node converts it by the field's type
    bus = bus_config(args)
    session = open_session(bus)
    try:
        answer = request_change(session, bus.keys, args.node, values, args.timeout)
    finally:
        close_session(session)
    if answer is None:
        log.error("no node answered on %s within %.1f s (is %s running, and does its kind take live changes?)",
                  bus.keys.config(args.node), args.timeout, args.node)
        return 1
    print(json.dumps({"node": answer.node, "applied": _from_json(answer.applied), "refused": answer.refused,
                      "params": _from_json(answer.params)}))
    return 1 if answer.refused else 0


def _from_json(values: dict[str, str]) -> dict[str, object]:
    """Values that travel as JSON text, as values (so they are not quoted twice when printed)."""
    return {name: json.loads(text) for name, text in values.items()}


def cmd_list(args: argparse.Namespace) -> int:
    from services.bus.discovery import live_nodes, node_reports
    from services.launcher.observe import format_nodes

    bus = bus_config(args)
    session = open_session(bus)
    try:
        nodes = live_nodes(session, bus.keys, args.timeout)
        states = node_reports(session, bus.keys, args.timeout) if nodes else []
    finally:
        close_session(session)
    if not nodes:
        print(f"no artrack nodes are up in namespace {bus.namespace!r}", file=sys.stderr)
        return 0
    print(format_nodes(nodes, states))
    return 0


def cmd_echo(args: argparse.Namespace) -> int:
    from services.launcher.observe import echo, print_json_lines

    bus = bus_config(args)
    key = bus.keys.resolve(args.key)
    session = open_session(bus)
    stop_on = signal.getsignal(signal.SIGTERM)
    signal.signal(signal.SIGTERM, signal.default_int_handler)
    try:
        printed = print_json_lines(echo(session, key, count=args.count, timeout_s=args.timeout,
                                        max_array_elements=None if args.full else 16))
    except (KeyboardInterrupt, BrokenPipeError):
        return 0
    finally:
        signal.signal(signal.SIGTERM, stop_on)
        close_session(session)
    if not printed:
        log.error("nothing arrived on %s in %g s", key, args.timeout)
        return EXIT_NOTHING
    return 0


def cmd_schemas(args: argparse.Namespace) -> int:
    import protocol  # noqa: F401  (registers every message)
    from protocol.schemas import write_schemas

    for path in write_schemas(args.out):
        print(path)
    return 0


def add_status(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("status", help="every supervised node's state, restarts and rates, client apps and "
                                      "their subscriptions; --check: exit 0 only when all nodes run")
    p.add_argument("--json", action="store_true", help="one JSON object instead of tables")
    p.add_argument("--check", action="store_true", help="exit 1 unless an `artrack up` or `artrack run` answered "
                   "and every node it supervises is running (a health check)")
    p.add_argument("--here", action="store_true", help="only the `artrack up` processes of this host")
    p.add_argument("--timeout", type=float, default=1.0, metavar="S", help="how long to wait for answers")
    add_bus_options(p)
    p.set_defaults(func=cmd_status)


def add_config(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("config", help="change a running node's live parameters (or show them, without --set)")
    p.add_argument("node", metavar="NODE", help="the node's name")
    p.add_argument("--set", action="append", metavar="FIELD=VALUE", help="a parameter to change, VALUE converted "
                   "by the field's type (a list or mapping as JSON); repeatable, applied all or none")
    p.add_argument("--timeout", type=float, default=2.0, metavar="S", help="how long to wait for the answer")
    add_bus_options(p)
    p.set_defaults(func=cmd_config)


def add_list(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("list", help="list the live nodes and their health")
    p.add_argument("--timeout", type=float, default=1.0, metavar="S", help="how long to wait for answers")
    add_bus_options(p)
    p.set_defaults(func=cmd_list)


def add_echo(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("echo", help="print the messages on a key as JSON lines")
    p.add_argument("key", help="key expression; relative to ar/<rig>/ unless it starts with the namespace")
    p.add_argument("--count", type=int, default=0, help="stop after this many messages")
    p.add_argument("--timeout", type=float, metavar="S", help="stop after S seconds without a message (exit 1 "
                   "when none arrived at all)")
    p.add_argument("--full", action="store_true", help="print whole arrays, not just dtype and shape of large ones")
    add_bus_options(p)
    p.set_defaults(func=cmd_echo)


def add_schemas(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("schemas", help="write the JSON Schema of every message to a folder")
    p.add_argument("out", type=Path, metavar="DIR")
    p.set_defaults(func=cmd_schemas)
