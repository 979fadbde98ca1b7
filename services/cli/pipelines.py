"""``artrack up``, ``node``, ``group``, ``router`` and ``demo``: the processes of a pipeline; ``artrack kinds`` and
``trackers``: what pipelines are made of."""

from __future__ import annotations

import argparse
import json
import os
import signal
import threading
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from pydantic import ValidationError

from services.bus.session import LOCAL_ROUTER
from services.cli.bus_options import add_bus_options, add_tls_options, bus_config, security_options
from services.launcher.pipeline import PipelineError, describe
from services.runtime.logs import log_format, setup_logging

if TYPE_CHECKING:
    from services.runtime.node import Node


def cmd_up(args: argparse.Namespace) -> int:
    from services.launcher.daemon import Daemon
    from services.launcher.pipeline import preflight, read_pipeline

    spec = read_pipeline(args.pipeline)
    preflight(spec, str(args.pipeline))
    daemon = Daemon(args.pipeline, spec, bus_config(args, daemon=True, defaults=spec.bus, source=str(args.pipeline)))
    stop, hup = threading.Event(), threading.Event()
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda *_: stop.set())
    signal.signal(signal.SIGHUP, lambda *_: hup.set())
    return daemon.run(stop, hup)


def cmd_router(args: argparse.Namespace) -> int:
    from services.bus.security import Security
    from services.launcher.router import router_config, run_router

    stop = threading.Event()
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda *_: stop.set())
    listen = tuple(args.listen or (LOCAL_ROUTER,))
    config = router_config(listen, tuple(args.connect or ()), args.zenoh_config,
                           security=Security(**security_options(args)), users=args.users, access=args.acl)
    run_router(config, stop, args.idle_exit)
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    from services.launcher.demo import run_demo

    chosen = {name: value for name, value in (("recording", args.recording), ("runs", args.runs)) if value}
    return run_demo(bus_config(args, defaults={"rig": f"demo-{os.getpid()}"}), **chosen)


def cmd_node(args: argparse.Namespace) -> int:
    from services.launcher.kinds import kind
    from services.runtime.flow import FlowPlan
    from services.runtime.node import run_node

    node_kind = kind(args.kind)
    try:
        params = node_kind.validate(json.loads(args.params))
    except json.JSONDecodeError as exc:
        raise PipelineError(f"--params is not JSON: {exc}") from exc
    except ValidationError as exc:
        raise PipelineError(f"node {args.name} ({args.kind}): {describe(exc)}") from exc
    try:
        flow = FlowPlan.model_validate_json(args.flow)
    except ValidationError as exc:
        raise PipelineError(f"node {args.name} ({args.kind}): --flow: {describe(exc)}") from exc
    setup_logging(log_format=log_format(args.log_format), node=args.name)
    return run_node(args.name, args.kind, bus_config(args, daemon=True), lambda node: node_kind.run(node, params), flow)


def cmd_group(args: argparse.Namespace) -> int:
    from services.launcher.kinds import kind
    from services.launcher.pipeline import GROUP_MEMBERS
    from services.runtime.group import Member, run_group

    try:
        listed = GROUP_MEMBERS.validate_json(args.nodes)
    except ValidationError as exc:
        raise PipelineError(f"process {args.name}: --nodes: {describe(exc)}") from exc
    members = []
    for member in listed:
        node_kind = kind(member.kind)
        try:
            params = node_kind.validate(member.params)
        except ValidationError as exc:
            raise PipelineError(f"node {member.name} ({member.kind}): {describe(exc)}") from exc
        members.append(Member(member.name, member.kind, _body(node_kind.run, params), member.flow, member.source))
    setup_logging(log_format=log_format(args.log_format), node=args.name,
                  members=frozenset(member.name for member in members))
    return run_group(args.name, bus_config(args, daemon=True), members)


def _body(run: Callable[[Node, Any], object], params: Any) -> Callable[[Node], object]:
    """A node body: ``run`` with ``params``."""
    return lambda node: run(node, params)


def cmd_kinds(args: argparse.Namespace) -> int:
    from services.launcher.kinds import catalogue, kind

    for name, module in sorted(catalogue().kinds.items()):
        print(f"{name:<12} {kind(name).summary}  ({module})")
    return 0


def cmd_trackers(args: argparse.Namespace) -> int:
    from services.launcher.kinds import catalogue
    from services.launcher.tracker import Tracker

    for name, path in sorted(catalogue().trackers.items()):
        chosen = Tracker.load(name)
        kinds = ", ".join(k for k, _, _ in chosen.models()) or "no node: the source alone"
        print(f"{name:<10} {chosen.summary}  [{kinds}]  ({path})")
    return 0


def add_up(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("up", help="run a pipeline file: every node its own process, restarted if it dies "
                                  "(within a budget); SIGHUP reloads live parameters")
    p.add_argument("pipeline", type=Path, metavar="PIPELINE.toml")
    add_bus_options(p)
    p.set_defaults(func=cmd_up)


def add_router(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("router", help="run a Zenoh router that hosts and local nodes meet through")
    p.add_argument("--listen", action="append", metavar="ENDPOINT", help=f"default {LOCAL_ROUTER}")
    p.add_argument("--connect", action="append", metavar="ENDPOINT", help="other routers to link with")
    p.add_argument("--zenoh-config", type=Path, metavar="FILE", help="a Zenoh config file (mode forced to router)")
    p.add_argument("--idle-exit", type=float, metavar="S", help="leave after S seconds with no session connected")
    add_tls_options(p.add_argument_group("security (see examples/secure)"))
    p.add_argument("--users", type=Path, metavar="FILE", help="user:password lines; sessions must log in as one")
    p.add_argument("--acl", type=Path, metavar="FILE", help="access file (TOML): who holds the pipeline and app roles")
    p.set_defaults(func=cmd_router)


def add_kinds(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("kinds", help="the node kinds found (with ARTRACK_PLUGINS, in those packages too)")
    p.set_defaults(func=cmd_kinds)


def add_trackers(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("trackers", help="the trackers found: pipeline templates `artrack run` fills")
    p.set_defaults(func=cmd_trackers)


def add_demo(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("demo", help="the bundled marker session tracked live and scored against ground truth, on "
                                    "a rig of its own (demo-PID unless --rig or ARTRACK_RIG); exit 130 if interrupted")
    p.add_argument("--recording", type=Path, metavar="IN.mcap", help="the recording to play (default: "
                   "recordings/markers.mcap)")
    p.add_argument("--runs", type=Path, metavar="DIR", help="where the run folder goes (default: runs/)")
    add_bus_options(p)
    p.set_defaults(func=cmd_demo)


def add_group(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("group", help="run several nodes in one process, messages between them passed by reference "
                                     "(what `up` and `run` start per process group)")
    p.add_argument("name", metavar="PROCESS", help="the process group's name")
    p.add_argument("--nodes", required=True, metavar="JSON", help="its nodes: a JSON list of {name, kind, params, "
                   "flow, source}")
    add_bus_options(p)
    p.set_defaults(func=cmd_group)


def add_node(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("node", help="run one node in the foreground (what `up` starts per node)")
    p.add_argument("kind", help="a node kind (`artrack kinds` lists them)")
    p.add_argument("--name", help="node name (default: the kind)")
    p.add_argument("--params", default="{}", metavar="JSON", help="the kind's parameters as a JSON object")
    p.add_argument("--flow", default="{}", metavar="JSON", help="the node's part in its pipeline's flow control "
                   "(a FlowPlan as JSON, set by `run` and `up`); default: real-time, none")
    add_bus_options(p)
    p.set_defaults(func=cmd_node)
