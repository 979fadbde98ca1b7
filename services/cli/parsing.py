"""The argument parser of every ``artrack`` command: a usage error is one line naming the option and what it
takes, and one line pointing at ``--help``, instead of the whole usage block."""

from __future__ import annotations

import argparse
import re
from typing import Any, NoReturn

EXIT_USAGE = 2
"""Exit status of a command line that cannot be parsed (argparse's own)."""

ARGUMENT = re.compile(r"^argument ([^:]+): ")


class Parser(argparse.ArgumentParser):
    """An ``argparse.ArgumentParser`` whose errors are ``PROG: --flag: problem`` and a ``--help`` hint on
    standard error, exit status 2. Subcommand parsers made with ``add_subparsers`` are of this class too."""

    def error(self, message: str) -> NoReturn:
        self.exit(EXIT_USAGE, f"{usage_error(self.prog, message)}\n(`{self.prog} --help` lists the options)\n")

    def _check_value(self, action: argparse.Action, value: Any) -> None:
        if action.choices is not None and value not in action.choices:
            choices = ", ".join(map(str, action.choices))
            raise argparse.ArgumentError(action, f"{value!r} is not one of {choices}")


def usage_error(prog: str, message: str) -> str:
    """The one line of argparse error ``message`` of command ``prog``: ``argument --x: ...`` as ``--x: ...``."""
    one_line = " ".join(message.split())
    return f"{prog}: " + ARGUMENT.sub(r"\1: ", one_line)
