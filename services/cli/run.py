"""``artrack run``: a source through a tracker, or a pipeline file, run as one job."""

from __future__ import annotations

import argparse
import logging
import shlex
from pathlib import Path
from typing import Any

from services.cli.bus_options import add_bus_options, bus_config
from services.cli.parsing import Parser
from services.runtime.outputs import check_output

log = logging.getLogger("artrack")


RUN_EXITS = ("exit codes: 0 done (or a live source stopped), 1 a node failed while running, 2 a bad option or "
             "a node that could not start, 3 the source is a damaged recording (played up to the damage), "
             "4 --strict and a frame was dropped or missing, 130 interrupted before a finite source ended "
             "(docs/configuration.md)")

SOURCE_SKIP = {"scene", "wait_for_subscriber"}
"""Capture fields ``artrack run`` does not make flags of: scene options have ``--scene-option``."""


def _run_parser(tracker: str) -> tuple[argparse.ArgumentParser, list, list]:
    """The parser of ``artrack run TRACKER``: source flags, the tracker's generated flags, job and bus options."""
    from services.launcher.flags import add_flags, flags_for
    from services.launcher.kinds import kind
    from services.launcher.tracker import Tracker

    chosen = Tracker.load(tracker)
    p = Parser(prog=f"artrack run {tracker}", epilog=RUN_EXITS, description=(
        f"{chosen.summary}. Processes: {chosen.layout()} (messages within a process pass by reference; "
        f"--processes separate or --process NODE= splits them out)"))
    source = flags_for(kind("capture").params, SOURCE_SKIP)
    add_flags(p.add_argument_group("source (a capture node; or --source recording:PATH.mcap, replayed on its own "
                                   "rig unless --rig/--namespace or ARTRACK_RIG/ARTRACK_NAMESPACE name another)"),
              source)
    p.add_argument("--scene-option", action="append", metavar="NAME=VALUE", help="a synthetic scene's option, "
                   "converted by its type (a list as JSON: ids=[1,2])")
    own = chosen.flags({flag.field: flag for flag in source})
    if own:
        add_flags(p.add_argument_group(f"{tracker} tracker (node kinds: "
                                       f"{', '.join(k for k, _, _ in chosen.models())})"), own)
    job = p.add_argument_group("job")
    job.add_argument("--record", type=Path, metavar="OUT.mcap", help="record every key of the rig to MCAP")
    job.add_argument("--rerun", type=Path, metavar="OUT.rrd", help="log the job to a Rerun file")
    job.add_argument("--record-foxglove", type=Path, metavar="OUT.mcap", help="write the job as it runs in "
                     "Foxglove's schemas (what `artrack export --format foxglove` makes of a recording), every "
                     "frame, to an MCAP file of its own")
    job.add_argument("--force", action="store_true", help="overwrite the --rerun, --record-foxglove and "
                     "--save-pipeline files if they exist (a --record recording is never overwritten)")
    job.add_argument("--save-pipeline", type=Path, metavar="FILE.toml", help="write the job as a pipeline file "
                     "(`artrack up FILE.toml` runs it as a daemon) and exit without running it")
    _display_options(job)
    add_bus_options(p)
    return p, source, own


def _display_options(group: argparse._ArgumentGroup) -> None:
    from services.launcher.layout import LAYOUTS

    group.add_argument("--flow", choices=("auto", "lossless", "realtime"),
                       help="lossless: every node takes every frame, the source waiting for the slowest (--fps is "
                       "then a ceiling; --fps 0: as fast as the slowest node); realtime: slow nodes drop frames "
                       "(latest-wins); auto (default): lossless when the source is finite (files, a recording, "
                       "a scene with --frames)")
    group.add_argument("--window", type=int, metavar="N", help="frames a lossless source may send ahead of its "
                       "slowest node (default 4)")
    group.add_argument("--processes", choices=LAYOUTS, default="given", help="given (default): the grouping of "
                       "nodes into processes the tracker or file gives; separate: every node its own process; "
                       "single: every node but the sinks (recorder, viewer, foxglove) in one process")
    group.add_argument("--process", action="append", default=[], metavar="NODE=NAME", help="run NODE in process "
                       "NAME, with the nodes placed there (NODE= alone: a process of its own); repeatable")
    group.add_argument("--nice", action="append", default=[], metavar="[NODE=]N", help="the priority of NODE's "
                       "process, -20 (most urgent) to 19 (without NODE=: every node but the sinks); below the "
                       "launcher's own it needs CAP_SYS_NICE or a nice limit (ulimit -e); repeatable")
    group.add_argument("--cpus", action="append", default=[], metavar="[NODE=]LIST", help="the CPUs NODE's process "
                       "may run on, such as 1 or 0,2-3 (without NODE=: every node but the sinks); repeatable")
    group.add_argument("--strict", action="store_true", help="exit 4 when any frame was dropped or went missing")
    group.add_argument("--progress", choices=("auto", "on", "off"), default="auto",
                       help="a progress line redrawn on standard error (auto: when it is a terminal)")
    group.add_argument("--quiet", action="store_true", help="no progress and no summary at the end")


def _display(args: argparse.Namespace):
    from services.launcher.progress import Display

    return Display.choose(args.progress, args.quiet)


def scene_option_texts(given: list[str] | None) -> dict[str, str]:
    """``--scene-option NAME=VALUE`` flags as ``{name: value text}``; ValueError for one without ``=``."""
    scene = {}
    for option in given or ():
        name, sep, value = option.partition("=")
        if not sep or not name:
            raise ValueError(f"--scene-option {option!r}: give NAME=VALUE")
        scene[name] = value
    return scene


def cmd_run(args: argparse.Namespace) -> int:
    from services.launcher.assembly import JobRequest, assemble, with_flow
    from services.launcher.flags import given_values
    from services.launcher.job import JobFile, run_job
    from services.launcher.kinds import catalogue
    from services.launcher.layout import laid_out, scheduled
    from services.launcher.pipeline import read_pipeline, save_pipeline
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
        spec = laid_out(with_flow(read_pipeline(Path(args.tracker)), _flow_given(run_args)), run_args.processes,
                        run_args.process)
        spec = scheduled(spec, run_args.nice, run_args.cpus)
        bus = bus_config(run_args, defaults=spec.bus, source=args.tracker)
        return run_job(bus, spec, args.tracker, _display(run_args), run_args.strict)
    p, source_flags, own_flags = _run_parser(args.tracker)
    run_args = p.parse_args(args.rest, namespace=args)
    given = given_values(run_args, source_flags)
    if not given.get("source"):
        p.error("give a --source (camera:N, video:PATH, images:DIR, synthetic:SCENE, rosbag2:DIR or "
                "recording:PATH.mcap)")
    bus, spec = assemble(JobRequest(
        tracker=args.tracker, source=given, bus=lambda defaults: bus_config(run_args, defaults=defaults),
        scene=scene_option_texts(run_args.scene_option), options=given_values(run_args, own_flags), flags=own_flags,
        source_flags=source_flags, record=run_args.record, flow=_flow_given(run_args),
        rerun=None if run_args.rerun is None else JobFile(run_args.rerun, run_args.force),
        foxglove=None if run_args.record_foxglove is None else JobFile(run_args.record_foxglove, run_args.force)))
    spec = scheduled(laid_out(spec, run_args.processes, run_args.process), run_args.nice, run_args.cpus)
    if run_args.save_pipeline is not None:
        check_output(run_args.save_pipeline, run_args.force)
        made_by = _command_line(["run", args.tracker, *args.rest], without="--save-pipeline")
        save_pipeline(spec, run_args.save_pipeline, f"Written by: {made_by}\nRun it with: artrack up "
                      f"{shlex.quote(str(run_args.save_pipeline))}")
        print(f"wrote {run_args.save_pipeline}: {len(spec.nodes)} nodes ({', '.join(spec.nodes)}); "
              f"run it with `artrack up {run_args.save_pipeline}`")
        return 0
    return run_job(bus, spec, f"artrack run {args.tracker}", _display(run_args), run_args.strict)


def _flow_given(args: argparse.Namespace) -> dict[str, Any]:
    """The flow fields given by ``--flow`` and ``--window``."""
    return {name: value for name, value in (("mode", args.flow), ("window", args.window)) if value is not None}


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
    p = Parser(prog=f"artrack run {path}", description="a pipeline file run as one job: its "
                                "sources start last, and the job ends when they do")
    _display_options(p.add_argument_group("job"))
    add_bus_options(p)
    return p


def add_run(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("run", add_help=False, help="one job: a source through a tracker (`artrack trackers` lists "
                       "them; `artrack run TRACKER --help` its options), optionally recorded")
    p.add_argument("tracker", nargs="?", metavar="TRACKER")
    p.set_defaults(func=cmd_run)
