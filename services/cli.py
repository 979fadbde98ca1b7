"""``artrack``: the command line of the tracking service."""

from __future__ import annotations

import argparse
import contextlib
import itertools
import json
import logging
import os
import signal
import socket
import sys
import threading
from collections.abc import Callable
from pathlib import Path

from pydantic import ValidationError

from protocol.system import ReplayCommand
from services.runtime.bus import LOCAL_ROUTER, BusConfig, BusError, open_session
from services.runtime.logs import FORMAT_ENV, FORMATS, log_format, setup_logging
from services.runtime.memory import tune_malloc
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
                       help="a Zenoh JSON5/YAML config, used as is but for the security options (env ZENOH_CONFIG)")
    group.add_argument("--namespace", help="key namespace (env ARTRACK_NAMESPACE; default ar)")
    group.add_argument("--rig", help="rig name (env ARTRACK_RIG; default rig0)")
    _tls_options(group)
    group.add_argument("--user", help="user name the router checks (env ARTRACK_USER; needs --mode client)")
    group.add_argument("--password-file", type=Path, metavar="FILE",
                       help="file holding the user's password (env ARTRACK_PASSWORD_FILE, or ARTRACK_PASSWORD)")


def _tls_options(group: argparse._ActionGroup) -> None:
    group.add_argument("--tls-ca", type=Path, metavar="PEM", help="root CA of tls/ endpoints (env ARTRACK_TLS_ROOT_CA)")
    group.add_argument("--tls-cert", type=Path, metavar="PEM", help="own certificate (env ARTRACK_TLS_CERT)")
    group.add_argument("--tls-key", type=Path, metavar="PEM", help="own private key (env ARTRACK_TLS_KEY)")
    group.add_argument("--tls-mutual", action="store_true", default=None,
                       help="mutual TLS: present the certificate / require one (env ARTRACK_TLS_MUTUAL)")


def _security(args: argparse.Namespace) -> dict[str, object]:
    """The security options given on the command line, by ``Security`` field."""
    given = {"root_ca": args.tls_ca, "cert": args.tls_cert, "key": args.tls_key, "mutual": args.tls_mutual,
             "user": getattr(args, "user", None), "password_file": getattr(args, "password_file", None)}
    return {field: value for field, value in given.items() if value is not None}


def _bus(args: argparse.Namespace, *, daemon: bool = False, **base: object) -> BusConfig:
    """Bus settings: environment, then ``base`` (a pipeline's ``[bus]``), then command-line options.

    A ``daemon`` (a node, ``up``) waits for its router unless ``ARTRACK_RETRY=0``."""
    if daemon and not os.environ.get("ARTRACK_RETRY"):
        base = {"retry": True, **base}
    given = {"connect": tuple(args.connect or ()), "listen": tuple(args.listen or ()), "mode": args.mode,
             "zenoh_config": args.zenoh_config, "namespace": args.namespace, "rig": args.rig,
             "security": _security(args) or None}
    # Only options actually given may override ``base``: an unset option must not erase a pipeline value.
    overrides = {**base, **{k: v for k, v in given.items() if v is not None and v != ()}}
    return BusConfig.from_env(**overrides)


def cmd_up(args: argparse.Namespace) -> int:
    from services.daemon import Daemon
    from services.launch import read_pipeline

    spec = read_pipeline(args.pipeline)
    daemon = Daemon(args.pipeline, spec, _bus(args, daemon=True, **spec.bus))
    stop, hup = threading.Event(), threading.Event()
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda *_: stop.set())
    signal.signal(signal.SIGHUP, lambda *_: hup.set())
    return daemon.run(stop, hup)


def cmd_status(args: argparse.Namespace) -> int:
    from services.status import HEALTHY, UNHEALTHY, format_status, gather

    bus = _bus(args)
    session = open_session(bus)
    try:
        status = gather(session, bus.keys, args.timeout)
    finally:
        session.close()
    if args.here:
        status = status.on_host(socket.gethostname())
    print(json.dumps(status.to_json()) if args.json else format_status(status))
    return (UNHEALTHY if status.problems() else HEALTHY) if args.check else 0


def cmd_config(args: argparse.Namespace) -> int:
    from services.runtime.reconfig import request_change

    values = {}
    for option in args.set or ():
        name, sep, text = option.partition("=")
        if not sep or not name:
            raise ValueError(f"--set {option!r}: give FIELD=VALUE")
        try:
            values[name] = json.loads(text)
        except json.JSONDecodeError:
            values[name] = text
    bus = _bus(args)
    session = open_session(bus)
    try:
        answer = request_change(session, bus.keys, args.node, values, args.timeout)
    finally:
        session.close()
    if answer is None:
        log.error("no node answered on %s within %.1f s (is %s running, and does its kind take live changes?)",
                  bus.keys.config(args.node), args.timeout, args.node)
        return 1
    print(json.dumps({"node": answer.node, "applied": answer.applied, "refused": answer.refused,
                      "params": answer.params}))
    return 1 if answer.refused else 0


def cmd_router(args: argparse.Namespace) -> int:
    from services.client.security import Security
    from services.runtime.router import router_config, run_router

    stop = threading.Event()
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda *_: stop.set())
    listen = tuple(args.listen or (LOCAL_ROUTER,))
    config = router_config(listen, tuple(args.connect or ()), args.zenoh_config, security=Security(**_security(args)),
                           users=args.users, access=args.acl)
    run_router(config, stop, args.idle_exit)
    return 0


def cmd_list(args: argparse.Namespace) -> int:
    from services.client.discovery import live_nodes, node_states
    from services.observe import format_nodes

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
    from services.observe import echo, print_json_lines

    bus = _bus(args)
    key = bus.keys.resolve(args.key)
    session = open_session(bus)
    stop_on = signal.getsignal(signal.SIGTERM)
    signal.signal(signal.SIGTERM, signal.default_int_handler)
    try:
        print_json_lines(echo(session, key, count=args.count, timeout_s=args.timeout,
                              max_array_elements=None if args.full else 16))
    except (KeyboardInterrupt, BrokenPipeError):
        pass
    finally:
        signal.signal(signal.SIGTERM, stop_on)
        session.close()
    return 0


def cmd_run(args: argparse.Namespace) -> int:
    from services.capture.node import Params as CaptureParams
    from services.jobs import RECORDING_SCHEME, JobError, Recording, run_job
    from services.pipelines import PIPELINES

    given = {name: getattr(args, name) for name in PIPELINES["marker"].options}
    options = {name: str(value) if isinstance(value, Path) else value for name, value in given.items()
               if value is not None}
    if any(uri.startswith(RECORDING_SCHEME) for uri in args.source):
        if len(args.source) > 1:
            raise JobError("a recording is the whole rig: give one --source recording:PATH and nothing else")
        return run_job(_bus(args), args.pipeline, Recording.open(args.source[0]), options, args.record, args.rerun)
    scene = {}
    for option in args.scene_option or ():
        name, _, value = option.partition("=")
        scene[name] = json.loads(value) if value[:1] in "0123456789-[{tf" else value
    capture = _params(CaptureParams, "capture", source=tuple(args.source), cameras=tuple(args.cameras or ()),
                      fps=args.fps, frames=args.frames, loop=args.loop or None, calib=tuple(args.calib or ()),
                      scene=scene, stamps=args.stamps)
    return run_job(_bus(args), args.pipeline, capture, options, args.record, args.rerun)


def cmd_demo(args: argparse.Namespace) -> int:
    from services.demo import run_demo

    chosen = {name: value for name, value in (("recording", args.recording), ("runs", args.runs)) if value}
    return run_demo(_bus(args), **chosen)


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
    setup_logging(log_format=log_format(args.log_format), node=args.name)
    return run_node(args.name, args.kind, _bus(args, daemon=True), lambda node: module.run(node, params))


def cmd_schemas(args: argparse.Namespace) -> int:
    import protocol  # noqa: F401  (registers every message)
    from protocol.schemas import write_schemas

    for path in write_schemas(args.out):
        print(path)
    return 0


def _params(cls: type, what: str, **values: object) -> object:
    """``cls`` (a node's Params) from the options given; unset (None) ones keep the model's defaults."""
    try:
        return cls(**{k: v for k, v in values.items() if v is not None})
    except ValidationError as exc:
        raise ValueError(f"{what}: {describe(exc)}") from exc


def _run_as_node(args: argparse.Namespace, kind: str, body: Callable[..., object]) -> int:
    """Run ``body(node)`` as node ``args.name`` of ``kind`` (logs tagged with the name)."""
    from services.runtime.node import run_node

    setup_logging(log_format=log_format(args.log_format), node=args.name)
    return run_node(args.name, kind, _bus(args), body)


def cmd_record(args: argparse.Namespace) -> int:
    from services.recorder.record_node import Params, run, subscriptions
    from services.recorder.writing import check_target

    params = _params(Params, "record", out=args.out, keys=tuple(args.keys or ()), split_size_mb=args.split_size,
                     split_duration_s=args.split_duration, queue_mb=args.queue_mb, flush_s=args.flush,
                     compression=args.compression)
    check_target(params.out)  # a bad output or overlapping keys fail here, before joining the bus
    subscriptions(_bus(args).keys, params.keys)
    return _run_as_node(args, "recorder", lambda node: run(node, params))


def cmd_replay(args: argparse.Namespace) -> int:
    from services.recorder.reading import Scan
    from services.recorder.replay_node import Params, Selection, run

    params = _params(Params, "replay", path=args.file, rate=args.rate, loop=args.loop, start_s=args.start,
                     end_s=args.end, keys=tuple(args.keys or ()), paused=args.paused, wait_s=args.wait)
    Scan(params.path)  # a missing or non-MCAP file fails here, before joining the bus
    Selection(_bus(args).keys, params.keys)  # and so does a bad key expression
    codes: list[int] = []
    failed = _run_as_node(args, "replay", lambda node: codes.append(run(node, params)))
    return failed or (codes[0] if codes else 0)


def cmd_control(args: argparse.Namespace) -> int:
    from services.recorder.replay_node import send_control

    bus = _bus(args)
    session = open_session(bus)
    try:
        answer = send_control(session, bus.keys, args.node, ReplayCommand(args.command), args.timeout)
    finally:
        session.close()
    if answer is None:
        log.error("no node answered on %s within %.1f s", bus.keys.control(args.node), args.timeout)
        return 1
    print(json.dumps(answer.model_dump(mode="json", exclude={"header"})))
    return 0


def cmd_info(args: argparse.Namespace) -> int:
    from services.recorder.info import format_info, summarise
    from services.recorder.reading import EXIT_DAMAGED, recover

    info = summarise(args.file)
    print(json.dumps(info.to_dict()) if args.json else format_info(info))
    if args.recover is not None:
        recovered = recover(args.file, args.recover)
        log.info("recovered %d messages into %s", recovered.messages, args.recover)
    return EXIT_DAMAGED if info.damage is not None else 0


def cmd_export(args: argparse.Namespace) -> int:
    from services.recorder.export import Export
    from services.recorder.reading import EXIT_DAMAGED

    job = Export(args.file, args.key, args.format, child=args.child, full=args.full)
    lines = job.lines()
    first = next(lines, None)  # a wrong key or format fails here, before the output is created
    with open(args.output, "w", newline="") if args.output else contextlib.nullcontext(sys.stdout) as out:
        for line in itertools.chain([] if first is None else [first], lines):
            out.write(line + "\n")
    log.info("exported %d rows of %s%s", job.rows, args.key,
             f" ({job.skipped} undecodable messages skipped)" if job.skipped else "")
    if job.damage is not None:
        log.warning("%s is damaged: %s; exported its intact part", args.file, job.damage)
        return EXIT_DAMAGED
    return 0


def cmd_view(args: argparse.Namespace) -> int:
    from services.recorder.reading import EXIT_DAMAGED
    from services.viewer.convert import convert
    from services.viewer.scene import ViewOptions

    options = _params(ViewOptions, "view", image_hz=args.image_hz, jpeg_quality=args.jpeg,
                      trajectory_length=args.trajectory, world_axes=args.world_axes)
    done = convert(args.file, args.out, options)
    log.info("wrote %s: %d rows from %d messages%s", args.out, done.rows, done.messages,
             f" ({done.undecodable} undecodable messages skipped)" if done.undecodable else "")
    if done.damage is not None:
        log.warning("%s is damaged: %s; converted its intact part", args.file, done.damage)
        return EXIT_DAMAGED
    return 0


IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm", ".webp")


def _image_files(where: str, pattern: str) -> list[Path]:
    """Image files of folder ``where`` matching ``pattern``, or those a glob ``where`` matches; sorted by path."""
    import glob

    folder = Path(where)
    candidates = folder.glob(pattern) if folder.is_dir() else (Path(p) for p in glob.glob(where))
    files = sorted(p for p in candidates if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)
    if not files:
        raise ValueError(f"no images ({', '.join(IMAGE_SUFFIXES)}) match {where}"
                         + (f" with --glob {pattern!r}" if folder.is_dir() else ""))
    return files


def cmd_calibrate(args: argparse.Namespace) -> int:
    import cv2

    from services.capture.calibration import write_camera_info
    from services.estimation.calibration import Charuco, Chessboard, calibrate_images

    columns, _, rows = args.size.lower().partition("x")
    if not (columns.isdigit() and rows.isdigit()):
        raise ValueError(f"--size {args.size!r}: give COLSxROWS, e.g. 9x6")
    if args.pattern == "chessboard":
        pattern = Chessboard(int(columns), int(rows), args.square)
    elif args.marker is None or args.dictionary is None:
        raise ValueError("--pattern charuco needs --marker and --dictionary")
    else:
        pattern = Charuco(int(columns), int(rows), args.square, args.marker, args.dictionary)
    files = _image_files(args.images, args.glob)
    images = ((path.name, cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)) for path in files)
    result = calibrate_images(images, pattern, args.camera)
    print(result.report())
    try:
        write_camera_info(args.out, result.camera)
    except OSError as exc:
        raise ValueError(f"cannot write {args.out}: {exc.strerror}") from exc
    print(f"wrote {args.out}")
    return 0


def parser() -> argparse.ArgumentParser:
    from services.catalog import KINDS
    from services.pipelines import PIPELINES

    top = argparse.ArgumentParser(prog="artrack", description="AR tracking service over Zenoh.")
    top.add_argument("--log-format", choices=FORMATS, help=f"log lines as text or JSON objects (env {FORMAT_ENV}; "
                     "default text); `up` passes it on to its nodes")
    sub = top.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("up", help="run a pipeline file: every node its own process, restarted if it dies "
                                  "(within a budget); SIGHUP reloads live parameters")
    p.add_argument("pipeline", type=Path, metavar="PIPELINE.toml")
    _bus_options(p)
    p.set_defaults(func=cmd_up)

    p = sub.add_parser("status", help="every supervised node's state, restarts and rates, client apps and "
                                      "their subscriptions; --check: exit 0 only when all nodes run")
    p.add_argument("--json", action="store_true", help="one JSON object instead of tables")
    p.add_argument("--check", action="store_true", help="exit 1 unless an `artrack up` answered and every node "
                   "it supervises is running (a health check)")
    p.add_argument("--here", action="store_true", help="only the `artrack up` processes of this host")
    p.add_argument("--timeout", type=float, default=1.0, metavar="S", help="how long to wait for answers")
    _bus_options(p)
    p.set_defaults(func=cmd_status)

    p = sub.add_parser("config", help="change a running node's live parameters (or show them, without --set)")
    p.add_argument("node", metavar="NODE", help="the node's name")
    p.add_argument("--set", action="append", metavar="FIELD=VALUE", help="a parameter to change, VALUE as JSON "
                   "(a bare word is a string); repeatable, applied all or none")
    p.add_argument("--timeout", type=float, default=2.0, metavar="S", help="how long to wait for the answer")
    _bus_options(p)
    p.set_defaults(func=cmd_config)

    p = sub.add_parser("router", help="run a Zenoh router that hosts and local nodes meet through")
    p.add_argument("--listen", action="append", metavar="ENDPOINT", help=f"default {LOCAL_ROUTER}")
    p.add_argument("--connect", action="append", metavar="ENDPOINT", help="other routers to link with")
    p.add_argument("--zenoh-config", type=Path, metavar="FILE", help="a Zenoh config file (mode forced to router)")
    p.add_argument("--idle-exit", type=float, metavar="S", help="leave after S seconds with no session connected")
    _tls_options(p.add_argument_group("security (see examples/secure)"))
    p.add_argument("--users", type=Path, metavar="FILE", help="user:password lines; sessions must log in as one")
    p.add_argument("--acl", type=Path, metavar="FILE", help="access file (TOML): who holds the pipeline and app roles")
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

    p = sub.add_parser("run", help="one job: capture from a source through a pipeline, optionally recorded")
    p.add_argument("pipeline", choices=sorted(PIPELINES),
                   help="; ".join(f"{name}: {pipeline.summary}" for name, pipeline in PIPELINES.items()))
    p.add_argument("--source", action="append", required=True, metavar="URI",
                   help="camera:N, video:PATH, images:DIR or synthetic:SCENE (repeat for a rig), "
                        "or recording:PATH.mcap (replayed on its own rig)")
    p.add_argument("--cameras", nargs="+", metavar="NAME", help="camera names (default: the source's, or cam0...)")
    p.add_argument("--fps", type=float, help="pace (default: the source's own timing)")
    p.add_argument("--frames", type=int, help="stop after this many frames")
    p.add_argument("--loop", action="store_true", help="start finite sources over when they end")
    p.add_argument("--calib", action="append", type=Path, metavar="FILE", help="ROS camera_info YAML, per camera")
    p.add_argument("--scene-option", action="append", metavar="NAME=VALUE", help="a synthetic scene's option")
    p.add_argument("--stamps", choices=("wall", "source"), help="stamp frames with capture or source time")
    marker = p.add_argument_group("marker pipeline")
    marker.add_argument("--dictionary", metavar="NAME", help="OpenCV dictionary name (e.g. DICT_5X5_100, "
                        "DICT_APRILTAG_36h11) or a custom dictionary YAML (default DICT_4X4_50)")
    marker.add_argument("--marker-length", type=float, metavar="M", help="marker side length in metres")
    marker.add_argument("--board", type=Path, metavar="FILE", help="a board / marker map YAML: one pose for all "
                        "its markers (see README)")
    marker.add_argument("--method", help="pose method (see README; default the most accurate on the tests)")
    marker.add_argument("--overlay", action="store_true", default=None,
                        help="also publish each camera's frames with a cube and axes drawn on every tracked "
                             "marker/board (key <camera>/overlay; logged by --rerun)")
    marker.add_argument("--depth", type=int, metavar="N", help="frames a marker node may queue while busy "
                        "(default 2: one frame waits, newer ones replace it; more tracks a recording whole "
                        "through long hiccups)")
    p.add_argument("--record", type=Path, metavar="OUT.mcap", help="record every key of the rig to MCAP")
    p.add_argument("--rerun", type=Path, metavar="OUT.rrd", help="log the job to a Rerun file")
    _bus_options(p)
    p.set_defaults(func=cmd_run)

    p = sub.add_parser("demo", help="the bundled marker session tracked live and scored against ground truth")
    p.add_argument("--recording", type=Path, metavar="IN.mcap", help="the recording to play (default: "
                   "recordings/markers.mcap)")
    p.add_argument("--runs", type=Path, metavar="DIR", help="where the run folder goes (default: runs/)")
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

    relative = "relative to ar/<rig>/ unless it starts with the namespace"
    p = sub.add_parser("record", help="record the rig's keys to MCAP until Ctrl-C (a node: `list` shows it)")
    p.add_argument("out", type=Path, metavar="OUT.mcap")
    p.add_argument("--keys", nargs="+", metavar="EXPR", help=f"key expressions to record, {relative} "
                                                             "(default: everything of the rig)")
    split = p.add_mutually_exclusive_group()
    split.add_argument("--split-size", type=float, metavar="MB",
                       help="write parts OUT_000.mcap, OUT_001.mcap, ... of about MB MiB each")
    split.add_argument("--split-duration", type=float, metavar="S", help="write parts of S seconds each (same names)")
    p.add_argument("--queue-mb", type=float, metavar="MB",
                   help="arrivals held while the writer is busy (default 512); beyond it they are dropped and counted")
    p.add_argument("--flush", type=float, metavar="S",
                   help="write out buffered data every S seconds (default 1): all a killed recorder can lose")
    p.add_argument("--compression", choices=("zstd", "lz4", "none"), help="chunk compression (default zstd)")
    p.add_argument("--name", default="recorder", help="node name (default recorder)")
    _bus_options(p)
    p.set_defaults(func=cmd_record)

    p = sub.add_parser("replay", help="publish a recording's bytes on their keys with their timing; exit 3 if damaged")
    p.add_argument("file", type=Path, metavar="IN.mcap")
    p.add_argument("--rate", type=float, metavar="R", help="speed factor (default 1)")
    p.add_argument("--loop", action="store_true", help="start again at the end, until Ctrl-C")
    p.add_argument("--start", type=float, metavar="S", help="begin S seconds into the recording")
    p.add_argument("--end", type=float, metavar="S", help="stop S seconds into the recording")
    p.add_argument("--keys", nargs="+", metavar="EXPR",
                   help=f"key expressions to replay, {relative} (default: all but node health, <namespace>/*/node/**)")
    p.add_argument("--paused", action="store_true", help="start paused; go on with `artrack control NAME resume`")
    p.add_argument("--wait", type=float, metavar="S", help="wait up to S seconds for a subscriber first (default 2)")
    p.add_argument("--name", default="replay", help="node name (default replay)")
    _bus_options(p)
    p.set_defaults(func=cmd_replay)

    p = sub.add_parser("control", help="pause, resume or step a replay node, or ask its status")
    p.add_argument("node", metavar="NODE", help="the node's name (replay unless --name was given)")
    p.add_argument("command", choices=[command.value for command in ReplayCommand])
    p.add_argument("--timeout", type=float, default=2.0, metavar="S", help="how long to wait for the answer")
    _bus_options(p)
    p.set_defaults(func=cmd_control)

    p = sub.add_parser("info", help="channels, counts, duration and rates of a recording (damaged too; exit 3 then)")
    p.add_argument("file", type=Path, metavar="IN.mcap")
    p.add_argument("--json", action="store_true", help="one JSON object instead of text")
    p.add_argument("--recover", type=Path, metavar="OUT.mcap", help="copy the intact part into a new, indexed file")
    p.set_defaults(func=cmd_info)

    p = sub.add_parser("export", help="one key of a recording as a TUM trajectory, CSV or JSON lines")
    p.add_argument("file", type=Path, metavar="IN.mcap")
    p.add_argument("--key", required=True, help="a recorded key, absolute or relative to the recording's ar/<rig>/")
    p.add_argument("--format", required=True, choices=("tum", "csv", "jsonl"))
    p.add_argument("-o", "--output", type=Path, metavar="OUT", help="output file (default: standard output)")
    p.add_argument("--child", metavar="FRAME", help="TUM: the child frame to export (needed for GroundTruth)")
    p.add_argument("--full", action="store_true", help="CSV / JSON lines: whole arrays, not dtype and shape")
    p.set_defaults(func=cmd_export)

    p = sub.add_parser("view", help="a recording as a Rerun .rrd file, drawn as the live viewer draws it "
                                    "(open it with `rerun OUT.rrd`; exit 3 if damaged)")
    p.add_argument("file", type=Path, metavar="IN.mcap")
    p.add_argument("out", type=Path, metavar="OUT.rrd")
    p.add_argument("--image-hz", type=float, metavar="HZ", help="at most HZ images per camera per second of "
                                                                 "recording (default: every frame)")
    p.add_argument("--jpeg", type=int, metavar="Q", help="store images as JPEG of quality Q (1-100), not raw pixels")
    p.add_argument("--trajectory", type=int, metavar="N", help="positions kept per trajectory line (default 300)")
    p.add_argument("--world-axes", metavar="XYZ", help="where the world frame's x, y, z point, in Rerun's letters "
                                                      "(default RDF, OpenCV's camera axes; RFU or FLU for z up)")
    p.set_defaults(func=cmd_view)

    p = sub.add_parser("calibrate", help="camera intrinsics from photos of a chessboard or ChArUco board, "
                                         "written as ROS camera_info YAML (exit 2 if the photos cannot constrain them)")
    p.add_argument("images", metavar="DIR_OR_GLOB", help="a folder of images, or a quoted glob like 'data/left*.jpg'")
    p.add_argument("--glob", default="*", metavar="PATTERN", help="in a folder, the files matching PATTERN (default *)")
    p.add_argument("--pattern", required=True, choices=("chessboard", "charuco"))
    p.add_argument("--size", required=True, metavar="COLSxROWS",
                   help="inner corners of a chessboard (e.g. 9x6), squares of a ChArUco board (e.g. 5x7)")
    p.add_argument("--square", required=True, type=float, metavar="M", help="side of a square, metres")
    p.add_argument("--marker", type=float, metavar="M", help="ChArUco: side of a marker, metres")
    p.add_argument("--dictionary", metavar="NAME", help="ChArUco: its markers' dictionary, e.g. DICT_6X6_250")
    p.add_argument("--camera", default="cam0", metavar="NAME", help="camera name written to the file (default cam0)")
    p.add_argument("--out", required=True, type=Path, metavar="CAMERA.yaml")
    p.set_defaults(func=cmd_calibrate)
    return top


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    if getattr(args, "name", "") is None:
        args.name = args.kind
    try:
        chosen = log_format(args.log_format)
    except ValueError as exc:
        print(f"artrack: {exc}", file=sys.stderr)
        return 2
    os.environ[FORMAT_ENV] = chosen  # processes started from here (`up`'s nodes) log the same way
    setup_logging(log_format=chosen)
    tune_malloc()
    try:
        return args.func(args)
    except (BusError, PipelineError, ValueError) as exc:
        log.error("%s", exc)
        return 2


if __name__ == "__main__":
    sys.exit(main())
