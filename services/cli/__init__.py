"""``artrack``: the command line of the tracking service, a thin dispatcher onto launcher/, recorder/,
calibration/, ...; each command sits in the module named for what it does, which adds its parser."""

from __future__ import annotations

import argparse
import logging
import os
import sys
from importlib import metadata

from services.bus.session import BusError
from services.cli import bodies, calibrate, markers, observe, pipelines, recordings, run, scenes, targets
from services.cli.markers import PAPER_NAMES
from services.cli.parsing import Parser
from services.launcher.pipeline import PipelineError
from services.runtime.logs import FORMAT_ENV, FORMATS, log_format, native_logs_to_stderr, setup_logging
from services.runtime.memory import tune_malloc

__all__ = ["PAPER_NAMES", "main", "parser"]

log = logging.getLogger("artrack")

COMMANDS = (pipelines.add_up, observe.add_status, observe.add_config, pipelines.add_router, observe.add_list,
            observe.add_echo, run.add_run, pipelines.add_kinds, pipelines.add_trackers, pipelines.add_demo,
            pipelines.add_node, pipelines.add_group, observe.add_schemas, recordings.add_record, recordings.add_replay,
            recordings.add_control, recordings.add_info, recordings.add_export, recordings.add_eval,
            recordings.add_view, calibrate.add_calibrate, markers.add_markers, scenes.add_scene, bodies.add_bodies,
            targets.add_target)
"""Each adds its command to ``artrack``'s subcommands, in the order ``artrack --help`` lists them."""


def parser() -> argparse.ArgumentParser:
    top = Parser(prog="artrack", description="AR tracking service over Zenoh.")
    top.add_argument("--version", action="version", version=f"artrack {metadata.version('artrack')}")
    top.add_argument("--log-format", choices=FORMATS, help=f"log lines as text or JSON objects (env {FORMAT_ENV}; "
                     "default text); `up` passes it on to its nodes")
    sub = top.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for add in COMMANDS:
        add(sub)
    _name_parsers(top)
    return top


def _name_parsers(parser: argparse.ArgumentParser) -> None:
    """Give each (sub)command's namespace the parser of the deepest command parsed (``command_parser``), so an
    argument none of them takes is refused by that command (``artrack export: unrecognized arguments: ...``)."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for command in action.choices.values():
                command.set_defaults(command_parser=command)
                _name_parsers(command)


LAZY = ("run", "record", "replay", "view")
"""Commands whose options come from a parameter model, parsed by the command itself from ``args.rest``."""


def main(argv: list[str] | None = None) -> int:
    top = parser()
    args, rest = top.parse_known_args(argv)
    if rest and args.command not in LAZY:
        args.command_parser.error(f"unrecognized arguments: {' '.join(rest)}")
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
    native_logs_to_stderr(chosen)
    tune_malloc()
    try:
        return args.func(args)
    except (BusError, PipelineError, ValueError) as exc:
        log.error("%s", exc)
        return 2
    except BrokenPipeError:  # the reader went away (`artrack info FILE | head`): nothing left to say
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
