"""``artrack``: the command line of the tracking service."""

from __future__ import annotations

import argparse
import json
import logging
import signal
import sys
import threading
from pathlib import Path

from pydantic import ValidationError

from services.runtime.bus import LOCAL_ROUTER, BusConfig, BusError, open_session
from services.runtime.logs import setup_logging
from services.runtime.pipeline import PipelineError, describe

log = logging.getLogger("artrack")


def _bus_options(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("bus (default: the local router on " + LOCAL_ROUTER + ", started on demand)")
    group.add_argument("--connect", action="append", metavar="ENDPOINT",
                       help="router or peer to connect to, e.g. tcp/10.0.0.5:7447 (repeatable; env ARTRACK_CONNECT)")
    group.add_argument("--listen", action="append", metavar="ENDPOINT",
                       help="endpoint to listen on (repeatable; env ARTRACK_LISTEN)")
    group.add_argument("--mode", choices=("peer", "client"), help="Zenoh mode (env ARTRACK_MODE; default peer)")
    group.add_argument("--zenoh-config", type=Path, metavar="FILE",
                       help="a Zenoh JSON5/YAML config, used as is (env ZENOH_CONFIG)")
    group.add_argument("--namespace", help="key namespace (env ARTRACK_NAMESPACE; default ar)")
    group.add_argument("--rig", help="rig name (env ARTRACK_RIG; default rig0)")


def _bus(args: argparse.Namespace, **base: object) -> BusConfig:
    """Bus settings: environment, then ``base`` (a pipeline's ``[bus]``), then command-line options."""
    given = {"connect": tuple(args.connect or ()), "listen": tuple(args.listen or ()), "mode": args.mode,
             "zenoh_config": args.zenoh_config, "namespace": args.namespace, "rig": args.rig}
    # Only options actually given may override ``base``: an unset option must not erase a pipeline value.
    overrides = {**base, **{k: v for k, v in given.items() if v is not None and v != ()}}
    return BusConfig.from_env(**overrides)


def cmd_up(args: argparse.Namespace) -> int:
    from services.launch import processes, read_pipeline
    from services.runtime.supervisor import Supervisor

    spec = read_pipeline(args.pipeline)
    bus = _bus(args, **spec.bus)
    supervisor = Supervisor(processes(spec, bus))
    stop = threading.Event()
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda *_: stop.set())
    log.info("pipeline %s: %d node(s) on %s", args.pipeline, len(spec.nodes), bus.keys.prefix)
    supervisor.start()
    supervisor.run(stop)
    log.info("pipeline %s stopped", args.pipeline)
    return 0


def cmd_router(args: argparse.Namespace) -> int:
    from services.runtime.router import router_config, run_router

    stop = threading.Event()
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda *_: stop.set())
    listen = tuple(args.listen or (LOCAL_ROUTER,))
    run_router(router_config(listen, tuple(args.connect or ()), args.zenoh_config), stop, args.idle_exit)
    return 0


def cmd_list(args: argparse.Namespace) -> int:
    from services.observe import format_nodes, live_nodes, node_states

    bus = _bus(args)
    session = open_session(bus)
    try:
        nodes = live_nodes(session, bus.keys, args.timeout)
        states = node_states(session, bus.keys, args.timeout) if nodes else {}
    finally:
        session.close()
    if not nodes:
        print(f"no artrack nodes are up in namespace {bus.namespace!r}", file=sys.stderr)
        return 0
    print(format_nodes(nodes, states))
    return 0


def cmd_echo(args: argparse.Namespace) -> int:
    from services.observe import echo, print_json_lines, resolve_key

    bus = _bus(args)
    session = open_session(bus)
    stop_on = signal.getsignal(signal.SIGTERM)
    signal.signal(signal.SIGTERM, signal.default_int_handler)
    try:
        key = resolve_key(bus.keys, args.key)
        print_json_lines(echo(session, key, count=args.count, timeout_s=args.timeout,
                              max_array_elements=None if args.full else 16))
    except (KeyboardInterrupt, BrokenPipeError):
        pass
    finally:
        signal.signal(signal.SIGTERM, stop_on)
        session.close()
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    from services.demo import run_demo

    return run_demo(_bus(args), args.frames, args.fps)


def cmd_node(args: argparse.Namespace) -> int:
    from services.catalog import kind
    from services.runtime.node import run_node

    node_kind = kind(args.kind)
    try:
        params = node_kind.params(json.loads(args.params))
    except json.JSONDecodeError as exc:
        raise PipelineError(f"--params is not JSON: {exc}") from exc
    except ValidationError as exc:
        raise PipelineError(f"node {args.name} ({args.kind}): {describe(exc)}") from exc
    module = node_kind.load()
    setup_logging(json_lines=args.log_json, node=args.name)
    return run_node(args.name, args.kind, _bus(args), lambda node: module.run(node, params))


def cmd_schemas(args: argparse.Namespace) -> int:
    import protocol  # noqa: F401  (registers every message)
    from protocol.schemas import write_schemas

    for path in write_schemas(args.out):
        print(path)
    return 0


def parser() -> argparse.ArgumentParser:
    from services.catalog import KINDS

    top = argparse.ArgumentParser(prog="artrack", description="AR tracking service over Zenoh.")
    top.add_argument("--log-json", action="store_true", default=None, help="log as JSON lines (env ARTRACK_LOG_JSON)")
    sub = top.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("up", help="run a pipeline file: every node its own process, restarted if it dies")
    p.add_argument("pipeline", type=Path, metavar="PIPELINE.toml")
    _bus_options(p)
    p.set_defaults(func=cmd_up)

    p = sub.add_parser("router", help="run a Zenoh router that hosts and local nodes meet through")
    p.add_argument("--listen", action="append", metavar="ENDPOINT", help=f"default {LOCAL_ROUTER}")
    p.add_argument("--connect", action="append", metavar="ENDPOINT", help="other routers to link with")
    p.add_argument("--zenoh-config", type=Path, metavar="FILE", help="a Zenoh config file (mode forced to router)")
    p.add_argument("--idle-exit", type=float, metavar="S", help="leave after S seconds with no session connected")
    p.set_defaults(func=cmd_router)

    p = sub.add_parser("list", help="list the live nodes and their health")
    p.add_argument("--timeout", type=float, default=1.0, metavar="S", help="how long to wait for answers")
    _bus_options(p)
    p.set_defaults(func=cmd_list)

    p = sub.add_parser("echo", help="print the messages on a key as JSON lines")
    p.add_argument("key", help="key expression; relative to ar/<rig>/ unless it starts with the namespace")
    p.add_argument("--count", type=int, default=0, help="stop after this many messages")
    p.add_argument("--timeout", type=float, metavar="S", help="stop after S seconds without a message")
    p.add_argument("--full", action="store_true", help="print whole arrays, not just dtype and shape of large ones")
    _bus_options(p)
    p.set_defaults(func=cmd_echo)

    p = sub.add_parser("demo", help="synthetic camera -> echo node -> client, printing what flowed")
    p.add_argument("--frames", type=int, default=300, help="frames to send (default 300)")
    p.add_argument("--fps", type=float, default=30.0, help="frame rate (default 30)")
    _bus_options(p)
    p.set_defaults(func=cmd_demo)

    p = sub.add_parser("node", help="run one node in the foreground (what `up` starts per node)")
    p.add_argument("kind", choices=sorted(KINDS), help="; ".join(f"{k.name}: {k.summary}" for k in KINDS.values()))
    p.add_argument("--name", help="node name (default: the kind)")
    p.add_argument("--params", default="{}", metavar="JSON", help="the kind's parameters as a JSON object")
    _bus_options(p)
    p.set_defaults(func=cmd_node)

    p = sub.add_parser("schemas", help="write the JSON Schema of every message to a folder")
    p.add_argument("out", type=Path, metavar="DIR")
    p.set_defaults(func=cmd_schemas)
    return top


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    if getattr(args, "name", "") is None:
        args.name = args.kind
    setup_logging(json_lines=args.log_json)
    try:
        return args.func(args)
    except (BusError, PipelineError, ValueError) as exc:
        log.error("%s", exc)
        return 2


if __name__ == "__main__":
    sys.exit(main())
