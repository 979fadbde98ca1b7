"""``artrack``: the command line of the tracking service."""

from __future__ import annotations

import argparse
import contextlib
import itertools
import json
import logging
import os
import shlex
import signal
import socket
import sys
import threading
from collections.abc import Callable, Mapping
from importlib import metadata
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

from pydantic import BaseModel, ValidationError

from protocol.system import ReplayCommand
from services.bus.session import LOCAL_ROUTER, BusConfig, BusError, open_session
from services.launcher.pipeline import PipelineError, describe
from services.runtime.logs import FORMAT_ENV, FORMATS, log_format, setup_logging
from services.runtime.memory import tune_malloc

if TYPE_CHECKING:
    import numpy as np

    from services.calibration.intrinsics import Pattern
    from services.geometry.camera import CameraModel
    from services.launcher.flags import Flag
    from services.recorder.export import Export
    from services.runtime.node import Node

log = logging.getLogger("artrack")

M = TypeVar("M", bound=BaseModel)


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


def _tls_options(group: argparse._ArgumentGroup) -> None:
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


def _bus(args: argparse.Namespace, *, daemon: bool = False, defaults: Mapping[str, object] | None = None,
         source: str | None = None) -> BusConfig:
    """Bus settings, each field from: its command-line option, else its environment variable, else
    ``defaults`` (the ``[bus]`` of pipeline file ``source``), else the field's default.

    When the environment overrides a value of file ``source``, one line says so. A ``daemon``
    (a node, ``up``) waits for its router unless ``ARTRACK_RETRY=0``."""
    defaults = {**({"retry": True} if daemon else {}), **(defaults or {})}
    given = {"connect": tuple(args.connect or ()), "listen": tuple(args.listen or ()), "mode": args.mode,
             "zenoh_config": args.zenoh_config, "namespace": args.namespace, "rig": args.rig,
             "security": _security(args) or None}
    # Only options actually given override what is below them: an unset option must not erase a value.
    overrides = {k: v for k, v in given.items() if v is not None and v != ()}
    try:
        bus = BusConfig.from_env(defaults=defaults, **overrides)
    except ValidationError as exc:
        variables = {field: name for name, field in BusConfig.ENVIRONMENT.variables().items()}
        problems = []
        for problem in exc.errors():
            field = ".".join(str(part) for part in problem["loc"])
            message = problem["msg"].removeprefix("Value error, ")
            if not field:
                problems.append(message)
                continue
            where = f"{field} (env {variables[field]})" if field in variables else field
            problems.append(f"{where}: {message} (given {problem['input']!r})")
        raise ValueError("bus settings: " + "; ".join(problems)) from exc
    beaten = bus.overridden(defaults, **overrides) if source is not None else {}
    if beaten:
        said = ", ".join(f"{field} by {variable}" + ("" if field.startswith("security") else f"={os.environ[variable]}")
                         for variable, field in beaten.items())
        log.warning("%s: the environment overrides [bus] %s (a flag beats the environment, which beats the file)",
                    source, said)
    return bus


def cmd_up(args: argparse.Namespace) -> int:
    from services.launcher.daemon import Daemon
    from services.launcher.pipeline import preflight, read_pipeline

    spec = read_pipeline(args.pipeline)
    preflight(spec, str(args.pipeline))
    daemon = Daemon(args.pipeline, spec, _bus(args, daemon=True, defaults=spec.bus, source=str(args.pipeline)))
    stop, hup = threading.Event(), threading.Event()
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda *_: stop.set())
    signal.signal(signal.SIGHUP, lambda *_: hup.set())
    return daemon.run(stop, hup)


def cmd_status(args: argparse.Namespace) -> int:
    from services.launcher.status import HEALTHY, UNHEALTHY, format_status, gather

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
    from services.launcher.reload import request_change

    values = {}
    for option in args.set or ():
        name, sep, text = option.partition("=")
        if not sep or not name:
            raise ValueError(f"--set {option!r}: give FIELD=VALUE")
        values[name] = text  # the node converts it by the field's type
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
    print(json.dumps({"node": answer.node, "applied": _from_json(answer.applied), "refused": answer.refused,
                      "params": _from_json(answer.params)}))
    return 1 if answer.refused else 0


def _from_json(values: dict[str, str]) -> dict[str, object]:
    """Values that travel as JSON text, as values (so they are not quoted twice when printed)."""
    return {name: json.loads(text) for name, text in values.items()}


def cmd_router(args: argparse.Namespace) -> int:
    from services.bus.security import Security
    from services.launcher.router import router_config, run_router

    stop = threading.Event()
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda *_: stop.set())
    listen = tuple(args.listen or (LOCAL_ROUTER,))
    config = router_config(listen, tuple(args.connect or ()), args.zenoh_config, security=Security(**_security(args)),
                           users=args.users, access=args.acl)
    run_router(config, stop, args.idle_exit)
    return 0


def cmd_list(args: argparse.Namespace) -> int:
    from services.bus.discovery import live_nodes, node_reports
    from services.launcher.observe import format_nodes

    bus = _bus(args)
    session = open_session(bus)
    try:
        nodes = live_nodes(session, bus.keys, args.timeout)
        states = node_reports(session, bus.keys, args.timeout) if nodes else []
    finally:
        session.close()
    if not nodes:
        print(f"no artrack nodes are up in namespace {bus.namespace!r}", file=sys.stderr)
        return 0
    print(format_nodes(nodes, states))
    return 0


def cmd_echo(args: argparse.Namespace) -> int:
    from services.launcher.observe import echo, print_json_lines

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


RUN_EXITS = ("exit codes: 0 done (or a live source stopped), 1 a node failed while running, 2 a bad option or "
             "a node that could not start, 3 the source is a damaged recording (played up to the damage), "
             "130 interrupted before a finite source ended (docs/configuration.md)")

SOURCE_SKIP = {"scene", "wait_for_subscriber"}
"""Capture fields ``artrack run`` does not make flags of: scene options have ``--scene-option``."""


def _run_parser(tracker: str) -> tuple[argparse.ArgumentParser, list, list]:
    """The parser of ``artrack run TRACKER``: source flags, the tracker's generated flags, job and bus options."""
    from services.launcher.flags import add_flags, flags_for
    from services.launcher.kinds import kind
    from services.launcher.tracker import Tracker

    chosen = Tracker.load(tracker)
    p = argparse.ArgumentParser(prog=f"artrack run {tracker}", description=chosen.summary, epilog=RUN_EXITS)
    source = flags_for(kind("capture").params, SOURCE_SKIP)
    add_flags(p.add_argument_group("source (a capture node; or --source recording:PATH.mcap, replayed on its own "
                                   "rig)"), source)
    p.add_argument("--scene-option", action="append", metavar="NAME=VALUE", help="a synthetic scene's option, "
                   "converted by its type (a list as JSON: ids=[1,2])")
    own = chosen.flags({flag.field: flag for flag in source})
    if own:
        add_flags(p.add_argument_group(f"{tracker} tracker (node kinds: "
                                       f"{', '.join(k for k, _, _ in chosen.models())})"), own)
    job = p.add_argument_group("job")
    job.add_argument("--record", type=Path, metavar="OUT.mcap", help="record every key of the rig to MCAP")
    job.add_argument("--rerun", type=Path, metavar="OUT.rrd", help="log the job to a Rerun file")
    job.add_argument("--save-pipeline", type=Path, metavar="FILE.toml", help="write the job as a pipeline file "
                     "(`artrack up FILE.toml` runs it as a daemon) and exit without running it")
    _display_options(job)
    _bus_options(p)
    return p, source, own


def _display_options(group: argparse._ArgumentGroup) -> None:
    group.add_argument("--progress", choices=("auto", "on", "off"), default="auto",
                       help="a progress line redrawn on standard error (auto: when it is a terminal)")
    group.add_argument("--quiet", action="store_true", help="no progress and no summary at the end")


def _display(args: argparse.Namespace):
    from services.launcher.progress import Display

    return Display.choose(args.progress, args.quiet)


def cmd_run(args: argparse.Namespace) -> int:
    from services.launcher.flags import explain, given_values
    from services.launcher.job import RECORDING_SCHEME, JobError, Recording, build_job, run_job
    from services.launcher.kinds import catalogue, kind
    from services.launcher.pipeline import NodeSpec, read_pipeline, save_pipeline
    from services.launcher.tracker import Tracker

    asked = args.tracker in ("-h", "--help") or (args.tracker is None and {"-h", "--help"} & set(args.rest))
    if args.tracker is None or asked:
        trackers = catalogue().trackers
        print("usage: artrack run TRACKER --source URI [options]   (artrack run TRACKER --help: its options)\n"
              "       artrack run PIPELINE.toml                     (a pipeline file run as one job)\ntrackers:")
        for name in sorted(trackers):
            print(f"  {name:<10} {Tracker.load(name).summary}")
        return 0 if asked else 2
    if args.tracker.endswith(".toml"):
        run_args = _pipeline_job_parser(args.tracker).parse_args(args.rest, namespace=args)
        spec = read_pipeline(Path(args.tracker))
        return run_job(_bus(run_args, defaults=spec.bus, source=args.tracker), spec, args.tracker, _display(run_args))
    p, source_flags, own_flags = _run_parser(args.tracker)
    run_args = p.parse_args(args.rest, namespace=args)
    given = given_values(run_args, source_flags)
    options = given_values(run_args, own_flags)
    sources = given.get("source", [])
    if not sources:
        p.error("give a --source (camera:N, video:PATH, images:DIR, synthetic:SCENE or recording:PATH.mcap)")
    if any(uri.startswith(RECORDING_SCHEME) for uri in sources):
        if len(sources) > 1 or len(given) > 1 or run_args.scene_option:
            raise JobError("a recording is the whole rig: give one --source recording:PATH and no other source "
                           "option")
        source: NodeSpec | Recording = Recording.open(sources[0])
    else:
        scene = {}
        for option in run_args.scene_option or ():
            name, sep, value = option.partition("=")
            if not sep or not name:
                raise ValueError(f"--scene-option {option!r}: give NAME=VALUE")
            scene[name] = value
        try:
            captured = kind("capture").validate({**given, "scene": scene})
        except ValidationError as exc:
            raise ValueError(explain(exc, source_flags, "source")) from exc
        source = NodeSpec(kind="capture", **given, **({"scene": scene} if scene else {}))
        options = _with_known_settings(options, own_flags, captured)
    spec = build_job(Tracker.load(args.tracker), source, options, own_flags, run_args.record, run_args.rerun)
    if run_args.save_pipeline is not None:
        made_by = _command_line(["run", args.tracker, *args.rest], without="--save-pipeline")
        save_pipeline(spec, run_args.save_pipeline, f"Written by: {made_by}\nRun it with: artrack up "
                      f"{shlex.quote(str(run_args.save_pipeline))}")
        print(f"wrote {run_args.save_pipeline}: {len(spec.nodes)} nodes ({', '.join(spec.nodes)}); "
              f"run it with `artrack up {run_args.save_pipeline}`")
        return 0
    bus = _bus(run_args, defaults=spec.bus)
    if isinstance(source, Recording):
        bus = source.on_bus(bus)
    return run_job(bus, spec, f"artrack run {args.tracker}", _display(run_args))


def _with_known_settings(options: dict[str, Any], flags: list[Flag], capture: BaseModel) -> dict[str, Any]:
    """``options`` with what the capture's sources settle (a markers scene's marker length) for the
    tracker's flags not given; each value taken said in one line."""
    from services.capture.sources import known_settings

    known = known_settings(capture.source, capture.scene)  # type: ignore[attr-defined]  # capture Params
    taken = dict(options)
    for flag in flags:
        if flag.field in known and not any(key.rpartition(".")[2] == flag.field for key in options):
            value, uri = known[flag.field]
            taken[flag.key] = value
            log.info("using %s %s, as %s renders it (give %s to override)", flag.option, value, uri, flag.option)
    return taken


def _command_line(argv: list[str], without: str) -> str:
    """``artrack ARGV...`` as a shell would take it, less the option ``without`` and its value."""
    kept, skip = [], False
    for arg in argv:
        if skip or arg == without or arg.startswith(without + "="):
            skip = arg == without and not skip
            continue
        kept.append(arg)
    return " ".join(shlex.quote(arg) for arg in ["artrack", *kept])


def _pipeline_job_parser(path: str) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=f"artrack run {path}", description="a pipeline file run as one job: its "
                                "sources start last, and the job ends when they do")
    _display_options(p.add_argument_group("job"))
    _bus_options(p)
    return p


def cmd_demo(args: argparse.Namespace) -> int:
    from services.launcher.demo import run_demo

    chosen = {name: value for name, value in (("recording", args.recording), ("runs", args.runs)) if value}
    return run_demo(_bus(args, defaults={"rig": f"demo-{os.getpid()}"}), **chosen)


def cmd_node(args: argparse.Namespace) -> int:
    from services.launcher.kinds import kind

    node_kind = kind(args.kind)
    try:
        params = node_kind.validate(json.loads(args.params))
    except json.JSONDecodeError as exc:
        raise PipelineError(f"--params is not JSON: {exc}") from exc
    except ValidationError as exc:
        raise PipelineError(f"node {args.name} ({args.kind}): {describe(exc)}") from exc
    setup_logging(log_format=log_format(args.log_format), node=args.name)
    return _node_exit(args.name, args.kind, _bus(args, daemon=True), lambda node: node_kind.run(node, params))


def _node_exit(name: str, kind: str, bus: BusConfig, body: Callable[[Node], object]) -> int:
    """``run_node``'s exit code, or the one ``body`` returned (a replay's 3 for a damaged file) when it is 0."""
    from services.runtime.node import run_node

    returned: list[object] = []
    failed = run_node(name, kind, bus, lambda node: returned.append(body(node)))
    code = returned[0] if returned else 0
    return failed or (code if isinstance(code, int) else 0)


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


def cmd_schemas(args: argparse.Namespace) -> int:
    import protocol  # noqa: F401  (registers every message)
    from protocol.schemas import write_schemas

    for path in write_schemas(args.out):
        print(path)
    return 0


def _run_as_node(args: argparse.Namespace, kind: str, body: Callable[[Node], object]) -> int:
    """Run ``body(node)`` as node ``args.name`` of ``kind`` (logs tagged with the name); see ``_node_exit``."""
    setup_logging(log_format=log_format(args.log_format), node=args.name)
    return _node_exit(args.name, kind, _bus(args), body)


def _from_flags(args: argparse.Namespace, prog: str, model: type[M], positional: dict[str, str], description: str,
                node: str | None = None) -> M:
    """``model`` from ``artrack PROG POSITIONAL... [flags]`` (``args.rest``): a flag per field of the model but
    the positional ones (paths), bus options and ``--name`` when it runs as a ``node``; errors name the flag."""
    from services.launcher.flags import add_flags, explain, flags_for, given_values

    p = argparse.ArgumentParser(prog=f"artrack {prog}", description=description)
    for field, metavar in positional.items():
        p.add_argument(field, type=Path, metavar=metavar)
    flags = flags_for(model, set(positional))
    add_flags(p.add_argument_group(f"{prog} options"), flags)
    if node is not None:
        p.add_argument("--name", default=node, help=f"node name (default {node})")
        _bus_options(p)
    parsed = p.parse_args(args.rest, namespace=args)
    fields = {f: getattr(parsed, f) for f in positional if f in model.model_fields}
    try:
        return model.model_validate({**fields, **given_values(parsed, flags)})
    except ValidationError as exc:
        raise ValueError(explain(exc, flags, prog)) from exc


RECORD_HELP = "record the rig's keys to MCAP until Ctrl-C (a node: `list` shows it)"
REPLAY_HELP = "publish a recording's bytes on their keys with their timing; exit 3 if damaged"
VIEW_HELP = ("a recording as a Rerun .rrd file, drawn as the live viewer draws it (open it with `rerun OUT.rrd`; "
             "exit 3 if damaged)")


def cmd_record(args: argparse.Namespace) -> int:
    from services.recorder.record_node import Params, run, subscriptions
    from services.recorder.writing import check_target

    params = _from_flags(args, "record", Params, {"out": "OUT.mcap"}, RECORD_HELP, node="recorder")
    check_target(params.out)  # a bad output or overlapping keys fail here, before joining the bus
    subscriptions(_bus(args).keys, params.keys)
    return _run_as_node(args, "recorder", lambda node: run(node, params))


def cmd_replay(args: argparse.Namespace) -> int:
    from services.recorder.reading import Scan
    from services.recorder.replay_node import Params, Selection, run

    params = _from_flags(args, "replay", Params, {"path": "IN.mcap"}, REPLAY_HELP, node="replay")
    Scan(params.path)  # a missing or non-MCAP file fails here, before joining the bus
    Selection(_bus(args).keys, params.keys)  # and so does a bad key expression
    return _run_as_node(args, "replay", lambda node: run(node, params))


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
    from services.recorder.export import export_path, is_expression, matching_keys
    from services.recorder.reading import EXIT_DAMAGED

    if not is_expression(args.key):
        job = _export_key(args, args.key, args.output)
        log.info("exported %d rows of %s%s", job.rows, args.key, _skipped(job.skipped))
    else:
        keys, prefix = matching_keys(args.file, args.key)
        folder = args.output or Path(".")
        if folder.exists() and not folder.is_dir():
            raise ValueError(f"-o {folder}: a key expression writes one file per key: give a folder")
        for key in keys:
            target = export_path(folder, key, prefix, args.format)
            job = _export_key(args, key, target)
            log.info("wrote %s: %d rows of %s%s", target, job.rows, key, _skipped(job.skipped))
        log.info("exported %d keys matching %s into %s", len(keys), args.key, folder)
    if job.damage is not None:
        log.warning("%s is damaged: %s; exported its intact part", args.file, job.damage)
        return EXIT_DAMAGED
    return 0


def _skipped(count: int) -> str:
    return f" ({count} undecodable messages skipped)" if count else ""


def _export_key(args: argparse.Namespace, key: str, output: Path | None) -> Export:
    """Export one recorded ``key`` of ``args.file`` into ``output`` (its folders made; None: standard output)."""
    from services.recorder.export import Export

    job = Export(args.file, key, args.format, child=args.child, full=args.full)
    lines = job.lines()
    first = next(lines, None)  # a wrong key or format fails here, before the output is created
    if output is not None:
        output.parent.mkdir(parents=True, exist_ok=True)
    with open(output, "w", newline="") if output else contextlib.nullcontext(sys.stdout) as out:
        for line in itertools.chain([] if first is None else [first], lines):
            out.write(line + "\n")
    return job


def cmd_eval(args: argparse.Namespace) -> int:
    from services.recorder.scoring import evaluate, format_evaluation
    from services.recorder.trajectories import load_trajectory

    est = load_trajectory(args.est, args.format, key=args.est_key, child=args.child)
    gt = load_trajectory(args.gt, args.format, key=args.gt_key, child=args.child)
    max_dt = {} if args.max_dt is None else {"max_dt_s": args.max_dt}
    evaluation = evaluate(est, gt, align=args.align, delta=args.delta, unit=args.delta_unit, **max_dt)
    if args.plot is not None:
        from services.recorder.trajectory_plot import plot_evaluation

        plot_evaluation(evaluation, args.plot)
    print(json.dumps(evaluation.to_dict()) if args.json else format_evaluation(evaluation))
    if args.plot is not None:
        log.info("wrote %s", args.plot)
    return 0


def cmd_view(args: argparse.Namespace) -> int:
    from services.recorder.reading import EXIT_DAMAGED
    from services.viewer.convert import convert
    from services.viewer.scene import ViewOptions

    options = _from_flags(args, "view", ViewOptions, {"file": "IN.mcap", "out": "OUT.rrd"}, VIEW_HELP)
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


def _calibration_pattern(args: argparse.Namespace) -> Pattern:
    """The target ``artrack calibrate``'s --pattern, --size, --square, --marker and --dictionary describe."""
    from services.calibration.intrinsics import Charuco, Chessboard

    columns, _, rows = args.size.lower().partition("x")
    if not (columns.isdigit() and rows.isdigit()):
        raise ValueError(f"--size {args.size!r}: give COLSxROWS, e.g. 9x6")
    if args.pattern == "chessboard":
        return Chessboard(int(columns), int(rows), args.square)
    if args.marker is None or args.dictionary is None:
        raise ValueError("--pattern charuco needs --marker and --dictionary")
    return Charuco(int(columns), int(rows), args.square, args.marker, args.dictionary)


def cmd_calibrate(args: argparse.Namespace) -> int:
    import cv2

    from services.calibration.camera_info import write_camera_info
    from services.calibration.intrinsics import calibrate_images

    if args.wand is not None:
        return cmd_calibrate_wand(args)
    missing = [flag for flag, value in (("DIR_OR_GLOB", args.images or None), ("--pattern", args.pattern),
                                        ("--size", args.size), ("--square", args.square)) if value is None]
    if missing:
        raise ValueError(f"calibrate needs {', '.join(missing)} (intrinsics from photos), or --wand (extrinsics)")
    if args.stereo:
        return _calibrate_stereo(args)
    if len(args.images) != 1:
        raise ValueError(f"one camera takes one DIR_OR_GLOB, got {len(args.images)}; "
                         "for a stereo pair add --stereo (LEFT RIGHT)")
    for option in ("names", "rig_frame", "refine_intrinsics"):
        if getattr(args, option) not in (None, False):
            raise ValueError(f"--{option.replace('_', '-')} is for --stereo")
    pattern = _calibration_pattern(args)
    files = _image_files(args.images[0], args.glob)
    images = ((path.name, cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)) for path in files)
    result = calibrate_images(images, pattern, args.camera)
    print(result.report())
    try:
        write_camera_info(args.out, result.camera)
    except OSError as exc:
        raise ValueError(f"cannot write {args.out}: {exc.strerror}") from exc
    print(f"wrote {args.out}")
    return 0


def cmd_calibrate_wand(args: argparse.Namespace) -> int:
    """Extrinsics of a recording's cameras from a wand waved before them, written as a rig file."""
    from dataclasses import replace

    import numpy as np

    from services.calibration.rig import Rig, write_rig
    from services.calibration.wand import Wand, calibrate_wand, reframe
    from services.convert import camera_model
    from services.recorder.camera_frames import camera_frames

    if args.wand_length is None or args.wand_middle is None:
        raise ValueError("--wand needs --wand-length (between the end spheres) and --wand-middle (the middle "
                         "sphere's distance from an end), metres")
    wand = Wand(np.array([0.0, args.wand_middle, args.wand_length]))
    recorded = camera_frames(args.wand, _ir_blobs)
    if len(recorded.cameras) < 2:
        raise ValueError(f"{args.wand}: wand calibration needs images of 2 or more cameras, found "
                         f"{recorded.cameras or 'none'}")
    given = _intrinsics(args.intrinsics or [])
    cameras = []
    for name in [c.name for c in given if c.name in recorded.cameras] or recorded.cameras:
        known = [c for c in given if c.name == name]
        if known:
            cameras.append(known[0])
        elif name in recorded.infos:
            cameras.append(camera_model(recorded.infos[name], name))
        else:
            raise ValueError(f"no intrinsics for camera {name!r}: the recording has no camera_info for it and "
                             "--intrinsics does not name it")
    names = [c.name for c in cameras]
    frames = [[frame.get(name, np.zeros((0, 2))) for name in names] for frame in recorded.frames.values()]
    result = calibrate_wand(cameras, frames, wand)
    print(result.report(names))
    placed = [replace(c, T_rig_camera=T) for c, T in zip(cameras, result.T_rig_camera, strict=True)]
    if args.floor is not None:
        T_rig_floor = _floor_frame(args.floor, placed)
        placed = [replace(c, T_rig_camera=T) for c, T in zip(cameras, reframe(result.T_rig_camera, T_rig_floor),
                                                              strict=True)]
    rig = Rig(args.out.stem, tuple(placed))
    try:
        write_rig(args.out, rig)
    except OSError as exc:
        raise ValueError(f"cannot write {args.out}: {exc.strerror}") from exc
    print(f"wrote {args.out}")
    return 0


def _ir_blobs(image: np.ndarray) -> np.ndarray:
    """(N, 2) centroids, px, of the clean blobs the IR detector finds in a mono (or BGR) image."""
    import cv2

    from services.detection.blobs import detect_ir_blobs

    mono = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image
    return detect_ir_blobs(mono).clean().centroids


def _floor_frame(path: Path, cameras: list[CameraModel]) -> np.ndarray:
    """(4, 4) ``T_rig_floor`` of the L-frame recorded in ``path``: its spheres triangulated with the
    calibrated ``cameras`` in every frame that shows exactly three, ordered, then the median."""
    import numpy as np

    from services.calibration.camera_info import CalibrationError
    from services.calibration.wand import floor_frame, order_lframe
    from services.estimation.correspondence import triangulate_blobs
    from services.recorder.camera_frames import camera_frames

    recorded = camera_frames(path, _ir_blobs)
    found = []
    for frame in recorded.frames.values():
        points = triangulate_blobs(cameras, [frame.get(c.name, np.zeros((0, 2))) for c in cameras])
        if len(points) == 3:
            with contextlib.suppress(CalibrationError):
                found.append(order_lframe(np.array([p.point for p in points])))
    if not found:
        raise ValueError(f"{path}: no frame shows the L-frame's three spheres (a right angle, unequal arms) "
                         "to two or more cameras")
    corner, on_x, on_y = np.median(found, axis=0)
    print(f"floor frame from {len(found)} of {len(recorded.frames)} frames of {path}: corner "
          f"({corner[0]:+.4f}, {corner[1]:+.4f}, {corner[2]:+.4f}) m in the first camera's frame")
    return floor_frame(corner, on_x, on_y)


def _intrinsics(files: list[Path]) -> list[CameraModel]:
    """Cameras of rig files and camera_info files, in the order given."""
    import yaml

    from services.calibration.camera_info import read_camera_info
    from services.calibration.rig import read_rig

    cameras: list[CameraModel] = []
    for path in files:
        try:
            is_rig = isinstance(document := yaml.safe_load(path.read_text()), dict) and "cameras" in document
        except (OSError, yaml.YAMLError):
            is_rig = False  # read_camera_info names the problem
        cameras += read_rig(path).cameras if is_rig else [read_camera_info(path)]
    return cameras


def _calibrate_stereo(args: argparse.Namespace) -> int:
    import cv2

    from services.calibration.rig import write_rig
    from services.calibration.stereo import calibrate_stereo

    if len(args.images) != 2:
        raise ValueError(f"--stereo needs the images of two cameras (LEFT RIGHT), got {len(args.images)}")
    names = tuple(name.strip() for name in (args.names or "cam0,cam1").split(","))
    if len(names) != 2 or not all(names):
        raise ValueError(f"--names {args.names!r}: give two camera names, e.g. left,right")
    pattern = _calibration_pattern(args)
    first, second = (_image_files(where, args.glob) for where in args.images)
    both = sorted(set(first) & set(second))
    if both:
        raise ValueError(f"{both[0]} is an image of both cameras: give each camera its own images")
    if len(first) != len(second):
        raise ValueError(f"{len(first)} images of {names[0]} ({args.images[0]}) but {len(second)} of {names[1]} "
                         f"({args.images[1]}): images are paired in name order, one per camera and pair")
    if args.rig_frame not in (None, *names):
        raise ValueError(f"--rig-frame {args.rig_frame!r} is none of the cameras ({', '.join(names)})")
    result = calibrate_stereo([(path.name, cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)) for path in first],
                              [(path.name, cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)) for path in second],
                              pattern, (names[0], names[1]), refine_intrinsics=args.refine_intrinsics)
    print(result.report())
    try:
        write_rig(args.out, result.rig(args.out.stem, args.rig_frame))
    except OSError as exc:
        raise ValueError(f"cannot write {args.out}: {exc.strerror}") from exc
    print(f"wrote {args.out} (rig frame: {args.rig_frame or names[0]})")
    return 0


def cmd_markers_print(args: argparse.Namespace) -> int:
    import cv2
    import yaml

    from services.detection.marker_sheet import (
        PAPERS,
        Sheet,
        board_document,
        charuco_sheet,
        grid_sheet,
        marker_sheet,
        parse_ids,
        write_pdf,
        write_png,
    )
    from services.detection.settings import DEFAULT_DICTIONARY

    suffix = args.out.suffix.lower()
    if args.paper not in PAPERS:
        raise ValueError(f"--paper {args.paper}: use one of {', '.join(PAPERS)}")
    dictionary = args.dictionary or DEFAULT_DICTIONARY
    if suffix not in (".pdf", ".png"):
        raise ValueError(f"-o {args.out}: give a .pdf or .png file")
    ids = parse_ids(args.ids) if args.ids is not None else None
    sheet: Sheet
    board: cv2.aruco.Board | None = None
    if args.board is None:
        sheet = marker_sheet(ids if ids is not None else [0], dictionary, args.length, args.paper)
    elif args.columns is None or args.rows is None:
        raise ValueError(f"--board {args.board} needs --columns and --rows")
    elif args.board == "grid":
        separation = args.separation if args.separation is not None else args.length / 4
        sheet, board = grid_sheet(args.columns, args.rows, args.length, separation, dictionary, ids, args.paper)
    elif args.square is None:
        raise ValueError("--board charuco needs --square (the side of a chessboard square, metres)")
    else:
        sheet, board = charuco_sheet(args.columns, args.rows, args.square, args.length, dictionary, ids,
                                     args.paper)
    try:
        (write_pdf if suffix == ".pdf" else write_png)(sheet, args.out, args.dpi)
    except OSError as exc:
        raise ValueError(f"cannot write {args.out}: {exc.strerror}") from exc
    print(f"wrote {args.out} ({args.paper}): print it at 100 % (actual size), then measure the scale bar")
    if board is not None:
        board_file = args.board_file or args.out.with_suffix(".yaml")
        try:
            board_file.write_text(yaml.safe_dump(board_document(board, args.name, dictionary), sort_keys=False,
                                                default_flow_style=None))
        except OSError as exc:
            raise ValueError(f"cannot write {board_file}: {exc.strerror}") from exc
        print(f"wrote {board_file}: pass it to `artrack run marker --board {board_file}`")
    return 0


def parser() -> argparse.ArgumentParser:
    top = argparse.ArgumentParser(prog="artrack", description="AR tracking service over Zenoh.")
    top.add_argument("--version", action="version", version=f"artrack {metadata.version('artrack')}")
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
    p.add_argument("--check", action="store_true", help="exit 1 unless an `artrack up` or `artrack run` answered "
                   "and every node it supervises is running (a health check)")
    p.add_argument("--here", action="store_true", help="only the `artrack up` processes of this host")
    p.add_argument("--timeout", type=float, default=1.0, metavar="S", help="how long to wait for answers")
    _bus_options(p)
    p.set_defaults(func=cmd_status)

    p = sub.add_parser("config", help="change a running node's live parameters (or show them, without --set)")
    p.add_argument("node", metavar="NODE", help="the node's name")
    p.add_argument("--set", action="append", metavar="FIELD=VALUE", help="a parameter to change, VALUE converted "
                   "by the field's type (a list or mapping as JSON); repeatable, applied all or none")
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

    p = sub.add_parser("run", add_help=False, help="one job: a source through a tracker (`artrack trackers` lists "
                       "them; `artrack run TRACKER --help` its options), optionally recorded")
    p.add_argument("tracker", nargs="?", metavar="TRACKER")
    p.set_defaults(func=cmd_run)

    p = sub.add_parser("kinds", help="the node kinds found (with ARTRACK_PLUGINS, in those packages too)")
    p.set_defaults(func=cmd_kinds)

    p = sub.add_parser("trackers", help="the trackers found: pipeline templates `artrack run` fills")
    p.set_defaults(func=cmd_trackers)

    p = sub.add_parser("demo", help="the bundled marker session tracked live and scored against ground truth, on "
                                    "a rig of its own (demo-PID unless --rig or ARTRACK_RIG); exit 130 if interrupted")
    p.add_argument("--recording", type=Path, metavar="IN.mcap", help="the recording to play (default: "
                   "recordings/markers.mcap)")
    p.add_argument("--runs", type=Path, metavar="DIR", help="where the run folder goes (default: runs/)")
    _bus_options(p)
    p.set_defaults(func=cmd_demo)

    p = sub.add_parser("node", help="run one node in the foreground (what `up` starts per node)")
    p.add_argument("kind", help="a node kind (`artrack kinds` lists them)")
    p.add_argument("--name", help="node name (default: the kind)")
    p.add_argument("--params", default="{}", metavar="JSON", help="the kind's parameters as a JSON object")
    _bus_options(p)
    p.set_defaults(func=cmd_node)

    p = sub.add_parser("schemas", help="write the JSON Schema of every message to a folder")
    p.add_argument("out", type=Path, metavar="DIR")
    p.set_defaults(func=cmd_schemas)

    p = sub.add_parser("record", add_help=False, help=RECORD_HELP)
    p.set_defaults(func=cmd_record)

    p = sub.add_parser("replay", add_help=False, help=REPLAY_HELP)
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

    p = sub.add_parser("export", help="keys of a recording as TUM trajectories, CSV or JSON lines")
    p.add_argument("file", type=Path, metavar="IN.mcap")
    p.add_argument("--key", required=True, help="a recorded key, or a key expression (pose/cam0/**) for one file "
                   "per matching key; absolute or relative to the recording's ar/<rig>/")
    p.add_argument("--format", required=True, choices=("tum", "csv", "jsonl"))
    p.add_argument("-o", "--output", type=Path, metavar="OUT", help="output file (default: standard output); with "
                   "a key expression, the folder of the files, each named after its key (default: .)")
    p.add_argument("--child", metavar="FRAME", help="TUM: the child frame to export (needed for GroundTruth)")
    p.add_argument("--full", action="store_true", help="CSV / JSON lines: whole arrays, not dtype and shape")
    p.set_defaults(func=cmd_export)

    p = sub.add_parser("eval", help="score an estimated trajectory against ground truth: ATE after alignment and "
                                    "RPE (TUM, KITTI pose files or a pose key of a recording)")
    p.add_argument("est", type=Path, metavar="EST", help="estimated trajectory: TUM, KITTI or .mcap file")
    p.add_argument("gt", type=Path, metavar="GT", help="ground truth: TUM, KITTI or .mcap file")
    p.add_argument("--align", default="se3", choices=("se3", "sim3", "none"),
                   help="Umeyama alignment of the estimate onto the truth (default se3; sim3 for monocular)")
    p.add_argument("--delta", type=float, default=1, metavar="N", help="RPE step (default 1)")
    p.add_argument("--delta-unit", default="frames", choices=("frames", "m"),
                   help="RPE step in matched frames or in metres travelled along the truth (default frames)")
    p.add_argument("--max-dt", type=float, metavar="S",
                   help="largest stamp difference of a matched pair, seconds (default 0.02, as TUM's tools)")
    p.add_argument("--format", choices=("tum", "kitti"), help="read EST and GT, when text files, as this format "
                                                              "(default: told apart by their column count)")
    p.add_argument("--est-key", metavar="KEY", help="the pose key when EST is a recording")
    p.add_argument("--gt-key", metavar="KEY", help="the pose key when GT is a recording")
    p.add_argument("--child", metavar="FRAME", help="recordings: the child frame (needed for GroundTruth keys)")
    p.add_argument("--plot", type=Path, metavar="OUT.png", help="draw both trajectories, top and side view "
                                                                "(needs the plot extra: matplotlib)")
    p.add_argument("--json", action="store_true", help="one JSON object instead of text")
    p.set_defaults(func=cmd_eval)

    p = sub.add_parser("view", add_help=False, help=VIEW_HELP)
    p.set_defaults(func=cmd_view)

    p = sub.add_parser("calibrate", help="camera intrinsics from photos of a chessboard or ChArUco board, "
                                         "written as ROS camera_info YAML (exit 2 if the photos cannot constrain "
                                         "them); with --stereo, two cameras and their relative pose, as a rig file; "
                                         "with --wand, a rig's extrinsics from a recorded wand, as a rig file")
    p.add_argument("images", nargs="*", metavar="DIR_OR_GLOB", help="a folder of images, or a quoted glob like "
                   "'data/left*.jpg'; with --stereo, one per camera (LEFT RIGHT), paired in name order")
    p.add_argument("--glob", default="*", metavar="PATTERN", help="in a folder, the files matching PATTERN (default *)")
    p.add_argument("--pattern", choices=("chessboard", "charuco"))
    p.add_argument("--size", metavar="COLSxROWS",
                   help="inner corners of a chessboard (e.g. 9x6), squares of a ChArUco board (e.g. 5x7)")
    p.add_argument("--square", type=float, metavar="M", help="side of a square, metres")
    p.add_argument("--marker", type=float, metavar="M", help="ChArUco: side of a marker, metres")
    p.add_argument("--dictionary", metavar="NAME", help="ChArUco: its markers' dictionary, e.g. DICT_6X6_250")
    p.add_argument("--camera", default="cam0", metavar="NAME", help="camera name written to the file (default cam0)")
    p.add_argument("-o", "--out", required=True, type=Path, metavar="CAMERA.yaml|RIG.yaml")
    p.add_argument("--wand", type=Path, metavar="RECORDING.mcap",
                   help="extrinsics from the IR images of a recording of a 3-sphere wand waved through the volume")
    p.add_argument("--wand-length", type=float, metavar="M", help="--wand: distance between its end spheres, metres")
    p.add_argument("--wand-middle", type=float, metavar="M",
                   help="--wand: distance of its middle sphere from one end, metres")
    p.add_argument("--intrinsics", nargs="+", type=Path, metavar="FILE",
                   help="--wand: rig or camera_info files of the cameras (default: the recording's camera_info)")
    p.add_argument("--floor", type=Path, metavar="LFRAME.mcap",
                   help="--wand: set the rig frame on an L-frame lying on the floor, recorded by the same cameras "
                        "(origin at its corner, x along its long arm, z up)")
    p.add_argument("--stereo", action="store_true", help="calibrate a stereo pair from image pairs: each camera's "
                   "intrinsics, then the pose between them (cv2.stereoCalibrate); --out is a rig file")
    p.add_argument("--names", metavar="A,B", help="--stereo: the two cameras' names (default cam0,cam1)")
    p.add_argument("--rig-frame", metavar="NAME", help="--stereo: the camera whose frame is the rig frame "
                   "(default the first)")
    p.add_argument("--refine-intrinsics", action="store_true", help="--stereo: let the stereo fit refine both "
                   "cameras' intrinsics (default: fixed at each camera's own calibration)")
    p.set_defaults(func=cmd_calibrate)

    markers = sub.add_parser("markers", help="marker utilities: `artrack markers print` draws printable sheets")
    markers_sub = markers.add_subparsers(dest="markers_command", required=True, metavar="ACTION")
    p = markers_sub.add_parser("print", help="a page of markers or a board at true scale (PDF or PNG), with the "
                               "board file the marker tracker reads")
    p.add_argument("-o", "--out", required=True, type=Path, metavar="SHEET.pdf|SHEET.png")
    p.add_argument("--dictionary", metavar="NAME", help="cv2.aruco dictionary (default: the marker tracker's, "
                   "DICT_4X4_50)")
    p.add_argument("--ids", metavar="LIST", help="ids and ranges, e.g. 0,1,2 or 0-5 (default 0; a board: 0, 1, ...)")
    p.add_argument("--length", required=True, type=float, metavar="M",
                   help="side of each marker's black square when printed, metres")
    p.add_argument("--paper", default="a4", choices=PAPER_NAMES, help="paper size (default a4)")
    p.add_argument("--dpi", type=float, default=300, help="PNG resolution, stored in the file; PDF: resolution "
                   "of the marker images placed at their exact size (default 300)")
    p.add_argument("--board", choices=("grid", "charuco"), help="one board instead of single markers: an ArUco "
                   "grid board or a ChArUco board")
    p.add_argument("--columns", type=int, metavar="N", help="board: markers (grid) or squares (charuco) per row")
    p.add_argument("--rows", type=int, metavar="N", help="board: rows of markers (grid) or squares (charuco)")
    p.add_argument("--separation", type=float, metavar="M", help="grid: gap between markers, metres "
                   "(default a quarter of --length)")
    p.add_argument("--square", type=float, metavar="M", help="charuco: side of a chessboard square, metres")
    p.add_argument("--name", default="board", help="board: its name, the pose key's last part (default board)")
    p.add_argument("--board-file", type=Path, metavar="BOARD.yaml", help="board: where its marker map goes "
                   "(default: beside the sheet, .yaml)")
    p.set_defaults(func=cmd_markers_print)
    return top


PAPER_NAMES = ("a4", "letter", "a3")
"""``artrack markers print --paper`` choices: ``marker_sheet.PAPERS``' names (that module loads OpenCV)."""
LAZY = ("run", "record", "replay", "view")
"""Commands whose options come from a parameter model, parsed by the command itself from ``args.rest``."""


def main(argv: list[str] | None = None) -> int:
    top = parser()
    args, rest = top.parse_known_args(argv)
    if rest and args.command not in LAZY:
        top.error(f"unrecognized arguments: {' '.join(rest)}")
    args.rest = rest
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
    except BrokenPipeError:  # the reader went away (`artrack info FILE | head`): nothing left to say
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0


if __name__ == "__main__":
    sys.exit(main())
