"""Where the tests find the real data sets: ``$ARTRACK_DATA``, else ``../shared/data`` beside the checkout.

A relative ``ARTRACK_DATA`` is taken relative to the repository root, as is the default.
Tests that need a data set call ``data_dir(name)``, which skips them, saying which folder is
missing and how to point at it, when the data is absent.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parent.parent
DEFAULT_DATA = Path("..") / "shared" / "data"


def data_root() -> Path:
    """The folder holding the data sets (it may not exist)."""
    root = Path(os.environ.get("ARTRACK_DATA") or DEFAULT_DATA)
    return root if root.is_absolute() else (REPO_ROOT / root).resolve()


def data_dir(name: str) -> Path:
    """The folder of data set ``name`` (e.g. ``calib_chessboard_stereo_opencv``); skips the test when absent."""
    folder = data_root() / name
    if not folder.is_dir():
        pytest.skip(f"data set {name!r} not found at {folder} (set ARTRACK_DATA to the folder holding the "
                    "shared data sets; see each set's SOURCE.md)")
    return folder
