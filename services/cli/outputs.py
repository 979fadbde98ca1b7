"""The one rule for files a command writes: an existing file is kept unless ``--force`` is given, and an output
that cannot be written is refused before the work that would fill it."""

from __future__ import annotations

import argparse
import os
from pathlib import Path

FORCE_HELP = "overwrite output files that exist (default: refuse them)"


def add_force_option(parser: argparse.ArgumentParser | argparse._ArgumentGroup) -> None:
    parser.add_argument("--force", action="store_true", help=FORCE_HELP)


def check_output(path: Path, force: bool, *, makes_folders: bool = False) -> None:
    """Refuse (ValueError, one line naming ``path``) an output that is a folder, that exists when not ``force``,
    or whose folder is missing (unless the command ``makes_folders``: then the nearest folder that exists)
    or not writable."""
    if path.is_dir():
        raise ValueError(f"{path} is a folder: give a file name")
    if path.exists() and not force:
        raise ValueError(f"{path} exists: give --force to overwrite it")
    folder = path.absolute().parent
    while makes_folders and not folder.exists() and folder != folder.parent:
        folder = folder.parent
    if not folder.is_dir():
        raise ValueError(f"cannot write {path}: " + (f"{folder} is not a folder" if folder.exists() else
                                                       f"folder {folder} does not exist"))
    if not os.access(folder, os.W_OK | os.X_OK):
        raise ValueError(f"cannot write {path}: folder {folder} is not writable")


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
