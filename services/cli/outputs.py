"""The command line's side of the rule for output files (``services.runtime.outputs``): the ``--force`` option, and
the same rule for output folders."""

from __future__ import annotations

import argparse
import os
from pathlib import Path

FORCE_HELP = "overwrite output files that exist (default: refuse them)"


def add_force_option(parser: argparse.ArgumentParser | argparse._ArgumentGroup) -> None:
    parser.add_argument("--force", action="store_true", help=FORCE_HELP)


def check_output_folder(path: Path, force: bool, *, marker: str) -> None:
    """Refuse (ValueError, one line naming ``path``) an output folder that exists when not ``force``, that is a
    file, or that exists but is not one this command writes (it holds no ``marker`` file: ``--force`` never
    removes a folder of something else); and one whose parent folder is missing or not writable."""
    if path.exists() and not path.is_dir():
        raise ValueError(f"{path} is a file: give a folder name")
    if path.is_dir() and not force:
        raise ValueError(f"{path} exists: give --force to overwrite it")
    if path.is_dir() and any(path.iterdir()) and not (path / marker).is_file():
        raise ValueError(f"{path} exists and has no {marker}: not overwriting a folder this command did not write")
    folder = path.absolute().parent
    if not folder.is_dir():
        raise ValueError(f"cannot write {path}: folder {folder} does not exist")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise ValueError(f"cannot write {path}: folder {folder} is not writable")
