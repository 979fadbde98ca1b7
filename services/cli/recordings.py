"""``artrack record``, ``replay`` and ``control``: recordings made and played on the bus; ``artrack info``,
``export``, ``eval`` and ``view``: tools on recorded files and trajectories."""

from __future__ import annotations

import argparse
import contextlib
import itertools
import json
import logging
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, TypeVar

from pydantic import BaseModel, ValidationError

from protocol.system import ReplayCommand
from services.bus.session import close_session, open_session
from services.cli.bus_options import add_bus_options, bus_config
from services.cli.outputs import add_force_option, check_output_folder
from services.cli.parsing import Parser
from services.runtime.logs import log_format, setup_logging
from services.runtime.outputs import check_output

if TYPE_CHECKING:
    from services.recorder.export import Export
    from services.runtime.node import Node

log = logging.getLogger("artrack")

M = TypeVar("M", bound=BaseModel)


def _run_as_node(args: argparse.Namespace, kind: str, body: Callable[[Node], object]) -> int:
    """Run ``body(node)`` as node ``args.name`` of ``kind`` (logs tagged with the name): its exit code
    (``services.runtime.node.serve``)."""
    from services.runtime.node import run_node

    setup_logging(log_format=log_format(args.log_format), node=args.name)
    return run_node(args.name, kind, bus_config(args), body)


def _from_flags(args: argparse.Namespace, prog: str, model: type[M], positional: dict[str, str], description: str,
                node: str | None = None, force: bool = False) -> M:
    """``model`` from ``artrack PROG POSITIONAL... [flags]`` (``args.rest``): a flag per field of the model but
    the positional ones (paths), bus options and ``--name`` when it runs as a ``node``, ``--force`` when it
    may overwrite its output (``args.force``); errors name the flag."""
    from services.launcher.flags import add_flags, explain, flags_for, given_values

    p = Parser(prog=f"artrack {prog}", description=description)
    for field, metavar in positional.items():
        p.add_argument(field, type=Path, metavar=metavar)
    flags = flags_for(model, set(positional))
    add_flags(p.add_argument_group(f"{prog} options"), flags)
    if force:
        add_force_option(p)
    if node is not None:
        p.add_argument("--name", default=node, help=f"node name (default {node})")
        add_bus_options(p)
    parsed = p.parse_args(args.rest, namespace=args)
    fields = {f: getattr(parsed, f) for f in positional if f in model.model_fields}
    try:
        return model.model_validate({**fields, **given_values(parsed, flags)})
    except ValidationError as exc:
        raise ValueError(explain(exc, flags, prog)) from exc


RECORD_HELP = "record the rig's keys to MCAP until Ctrl-C (a node: `list` shows it)"
REPLAY_HELP = "publish a recording's bytes on their keys with their timing; exit 3 if damaged"
VIEW_HELP = ("a recording as a Rerun .rrd file, drawn as the live viewer draws it (open it with `rerun OUT.rrd`; "
             "exit 3 if damaged); with --foxglove, the rig served live to Foxglove")
FOXGLOVE_HELP = ("serve the rig live over Foxglove's WebSocket protocol until Ctrl-C (a node: `list` shows it); "
                 "connect Foxglove to ws://127.0.0.1:8765. With --mcap FILE it also writes what it serves, every "
                 "frame, to a Foxglove MCAP file (--no-serve: the file only)")


def cmd_record(args: argparse.Namespace) -> int:
    from services.recorder.record_node import Params, run, subscriptions
    from services.recorder.writing import check_target

    params = _from_flags(args, "record", Params, {"out": "OUT.mcap"}, RECORD_HELP, node="recorder")
    check_target(params.out)  # a bad output or overlapping keys fail here, before joining the bus
    subscriptions(bus_config(args).keys, params.keys)
    return _run_as_node(args, "recorder", lambda node: run(node, params))


def cmd_replay(args: argparse.Namespace) -> int:
    from services.recorder.reading import Scan
    from services.recorder.replay_node import Params, Selection, run

    params = _from_flags(args, "replay", Params, {"path": "IN.mcap"}, REPLAY_HELP, node="replay")
    Scan(params.path)  # a missing or non-MCAP file fails here, before joining the bus
    Selection(bus_config(args).keys, params.keys)  # and so does a bad key expression
    return _run_as_node(args, "replay", lambda node: run(node, params))


def cmd_control(args: argparse.Namespace) -> int:
    from services.recorder.replay_node import send_control

    bus = bus_config(args)
    session = open_session(bus)
    try:
        answer = send_control(session, bus.keys, args.node, ReplayCommand(args.command), args.timeout)
    finally:
        close_session(session)
    if answer is None:
        log.error("no node answered on %s within %.1f s", bus.keys.control(args.node), args.timeout)
        return 1
    print(json.dumps(answer.model_dump(mode="json", exclude={"header"})))
    return 0


def cmd_info(args: argparse.Namespace) -> int:
    from services.recorder.info import format_info, summarise
    from services.recorder.reading import EXIT_DAMAGED, recover
    from services.recorder.writing import check_target

    if args.recover is not None:
        check_target(args.recover)  # before reading: a recording is never overwritten, the one read least of all
    info = summarise(args.file)
    print(json.dumps(info.to_dict()) if args.json else format_info(info))
    if args.recover is not None:
        recovered = recover(args.file, args.recover)
        log.info("recovered %d messages into %s", recovered.messages, args.recover)
    return EXIT_DAMAGED if info.damage is not None else 0


def cmd_export(args: argparse.Namespace) -> int:
    from services.recorder.export import export_path, is_expression, matching_keys
    from services.recorder.reading import EXIT_DAMAGED

    if args.format == "foxglove":
        return _export_foxglove(args)
    if args.compressed:
        raise ValueError("--compressed is for --format foxglove")
    if args.format == "rosbag2":
        return _export_rosbag(args)
    if args.key is None:
        raise ValueError(f"--format {args.format} exports one key or a key expression: give --key")
    if not is_expression(args.key):
        if args.output is not None:
            check_output(args.output, args.force, makes_folders=True)
        job = _export_key(args, args.key, args.output)
        log.info("exported %d rows of %s%s", job.rows, args.key, _skipped(job.skipped))
    else:
        keys, prefix = matching_keys(args.file, args.key)
        folder = args.output or Path(".")
        if folder.exists() and not folder.is_dir():
            raise ValueError(f"-o {folder}: a key expression writes one file per key: give a folder")
        targets = {key: export_path(folder, key, prefix, args.format) for key in keys}
        for target in targets.values():
            check_output(target, args.force, makes_folders=True)
        for key, target in targets.items():
            job = _export_key(args, key, target)
            log.info("wrote %s: %d rows of %s%s", target, job.rows, key, _skipped(job.skipped))
        log.info("exported %d keys matching %s into %s", len(keys), args.key, folder)
    if job.damage is not None:
        log.warning("%s is damaged: %s; exported its intact part", args.file, job.damage)
        return EXIT_DAMAGED
    return 0


def _export_foxglove(args: argparse.Namespace) -> int:
    """The whole recording ``args.file`` rewritten with Foxglove's schemas into ``args.output``."""
    from services.viewer.foxglove_export import export_foxglove
    from services.viewer.foxglove_messages import FoxgloveOptions

    given = [flag for flag, value in (("--key", args.key), ("--child", args.child), ("--full", args.full)) if value]
    if given:
        raise ValueError(f"--format foxglove converts the whole recording: {', '.join(given)} does not apply")
    if args.output is None:
        raise ValueError("--format foxglove writes an MCAP file: give -o OUT.mcap")
    check_output(args.output, args.force)
    done = export_foxglove(args.file, args.output, FoxgloveOptions(compressed=args.compressed))
    log.info("wrote %s: %d messages on %d topics from %d recorded%s", args.output, done.written.total(),
             len(done.written), done.read, _skipped(done.undecodable))
    return _outcome(args.file, done.damage, "exported")


def _export_rosbag(args: argparse.Namespace) -> int:
    """``export --format rosbag2``: the whole recording as a ROS 2 bag in folder ``-o``."""
    import shutil

    from services.recorder.reading import Scan
    from services.recorder.rosbag import export_rosbag

    if args.key is not None or args.output is None:
        raise ValueError("--format rosbag2 writes the whole recording into the bag folder -o DIR: give -o and no --key")
    check_output_folder(args.output, args.force, marker="metadata.yaml")
    Scan(args.file)  # a missing or non-MCAP file fails here, before the old bag is removed
    if args.output.exists():
        shutil.rmtree(args.output)
    done = export_rosbag(args.file, args.output)
    for topic, count in sorted(done.topics.items()):
        log.info("%s: %d %s", topic, count, done.types[topic])
    if done.left_out:
        log.info("left out (no ROS form): %s", ", ".join(f"{key} ({n})" for key, n in sorted(done.left_out.items())))
    log.info("wrote %s: %d messages on %d topics%s", args.output, sum(done.topics.values()), len(done.topics),
             _skipped(done.undecodable))
    return _outcome(args.file, done.damage, "exported")


def _outcome(source: Path, damage: object, done: str) -> int:
    """The exit code of a file tool that read ``source``: 0, or ``EXIT_DAMAGED`` after one warning line saying
    ``damage`` (None: intact) and that the intact part was ``done`` (exported, converted)."""
    from services.recorder.reading import EXIT_DAMAGED

    if damage is None:
        return 0
    log.warning("%s is damaged: %s; %s its intact part", source, damage, done)
    return EXIT_DAMAGED


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
    from services.recorder.reading import EXIT_DAMAGED
    from services.recorder.scoring import evaluate, format_evaluation
    from services.recorder.trajectories import load_trajectory

    est = load_trajectory(args.est, args.format, key=args.est_key, child=args.child)
    gt = load_trajectory(args.gt, args.format, key=args.gt_key, child=args.gt_child or args.child)
    max_dt = {} if args.max_dt is None else {"max_dt_s": args.max_dt}
    evaluation = evaluate(est, gt, align=args.align, delta=args.delta, unit=args.delta_unit, by=args.match_by,
                          **max_dt)
    if args.plot is not None:
        from services.recorder.trajectory_plot import plot_evaluation

        plot_evaluation(evaluation, args.plot)
    print(json.dumps(evaluation.to_dict()) if args.json else format_evaluation(evaluation))
    if args.plot is not None:
        log.info("wrote %s", args.plot)
    damaged = {path: trajectory.damage for path, trajectory in ((args.est, est), (args.gt, gt))
               if trajectory.damage is not None}
    for path, damage in damaged.items():
        log.warning("%s is damaged: %s; scored its intact part", path, damage)
    return EXIT_DAMAGED if damaged else 0


def cmd_view(args: argparse.Namespace) -> int:

    if "--foxglove" in args.rest:
        args.rest.remove("--foxglove")
        return _serve_foxglove(args)
    from services.viewer.convert import convert
    from services.viewer.scene import ViewOptions

    options = _from_flags(args, "view", ViewOptions, {"file": "IN.mcap", "out": "OUT.rrd"}, VIEW_HELP, force=True)
    check_output(args.out, args.force)
    done = convert(args.file, args.out, options)
    log.info("wrote %s: %d rows from %d messages%s", args.out, done.rows, done.messages, _skipped(done.undecodable))
    return _outcome(args.file, done.damage, "converted")


def _serve_foxglove(args: argparse.Namespace) -> int:
    from services.viewer.foxglove_node import KIND, Params, run

    params = _from_flags(args, "view --foxglove", Params, {}, FOXGLOVE_HELP, node="foxglove")
    KIND.preflight(params)  # an existing or unwritable file fails here, before joining the bus
    return _run_as_node(args, "foxglove", lambda node: run(node, params))


def add_record(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("record", add_help=False, help=RECORD_HELP)
    p.set_defaults(func=cmd_record)


def add_replay(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("replay", add_help=False, help=REPLAY_HELP)
    p.set_defaults(func=cmd_replay)


def add_control(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("control", help="pause, resume or step a replay node, or ask its status")
    p.add_argument("node", metavar="NODE", help="the node's name (replay unless --name was given)")
    p.add_argument("command", choices=[command.value for command in ReplayCommand])
    p.add_argument("--timeout", type=float, default=2.0, metavar="S", help="how long to wait for the answer")
    add_bus_options(p)
    p.set_defaults(func=cmd_control)


def add_info(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("info", help="channels, counts, duration and rates of a recording (damaged too; exit 3 then)")
    p.add_argument("file", type=Path, metavar="IN.mcap")
    p.add_argument("--json", action="store_true", help="one JSON object instead of text")
    p.add_argument("--recover", type=Path, metavar="OUT.mcap", help="copy the intact part into a new, indexed file")
    p.set_defaults(func=cmd_info)


def add_export(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("export", help="keys of a recording as TUM trajectories, CSV or JSON lines; the whole "
                                      "recording for Foxglove or as a ROS 2 bag")
    p.add_argument("file", type=Path, metavar="IN.mcap")
    p.add_argument("--key", help="a recorded key, or a key expression (pose/cam0/**) for one file per matching "
                   "key; absolute or relative to the recording's ar/<rig>/ (not with foxglove or rosbag2)")
    p.add_argument("--format", required=True, choices=("tum", "csv", "jsonl", "foxglove", "rosbag2"),
                   help="foxglove: every message as Foxglove's schemas (images, calibrations, transforms, poses, "
                        "points, detections, logs) into one MCAP file, -o OUT.mcap; rosbag2: every message with "
                        "a ROS 2 form, into the bag folder -o (docs/ros2.md)")
    p.add_argument("-o", "--output", type=Path, metavar="OUT", help="output file (default: standard output); with "
                   "a key expression, the folder of the files, each named after its key (default: .); "
                   "rosbag2: the bag's folder")
    p.add_argument("--child", metavar="FRAME", help="TUM: the child frame to export (needed for GroundTruth)")
    p.add_argument("--full", action="store_true", help="CSV / JSON lines: whole arrays, not dtype and shape")
    p.add_argument("--compressed", action="store_true", help="foxglove: images as JPEG (mono16 as PNG), not raw")
    add_force_option(p)
    p.set_defaults(func=cmd_export)


def add_eval(sub: argparse._SubParsersAction) -> None:
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
    p.add_argument("--match-by", default="auto", choices=("auto", "stamp", "frame", "index"),
                   help="pair poses by stamp, by frame number (KITTI rows, a recording's seq) or by index (row i "
                        "with row i); default auto: by stamp, else frame number, else index when neither is on "
                        "both sides and the counts are equal. Fewer than half the estimate's poses paired "
                        "(or fewer than 3) is refused, exit 2")
    p.add_argument("--format", choices=("tum", "kitti"), help="read EST and GT, when text files, as this format "
                                                              "(default: told apart by their column count)")
    p.add_argument("--est-key", metavar="KEY", help="the pose key when EST is a recording")
    p.add_argument("--gt-key", metavar="KEY", help="the pose key when GT is a recording")
    p.add_argument("--child", metavar="FRAME", help="recordings: the child frame (needed for GroundTruth keys)")
    p.add_argument("--gt-child", metavar="FRAME", help="recordings: GT's child frame when it is named otherwise than "
                                                      "EST's (default --child), e.g. a scene's `target` against "
                                                      "the features tracker's `target/NAME`")
    p.add_argument("--plot", type=Path, metavar="OUT.png", help="draw both trajectories, top and side view, "
                                                                "to a PNG")
    p.add_argument("--json", action="store_true", help="one JSON object instead of text")
    p.set_defaults(func=cmd_eval)


def add_view(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("view", add_help=False, help=VIEW_HELP)
    p.set_defaults(func=cmd_view)
