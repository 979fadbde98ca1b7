"""The one rule for files artrack writes: an existing file is kept unless its writer is told to overwrite it (a
command's ``--force``, a node's ``force``), and an output that cannot be written is refused before the work that
would fill it."""

from __future__ import annotations

import os
from pathlib import Path


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
