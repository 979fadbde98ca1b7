"""Image folders as data sets lay them out: a folder's image files, in order, with their times.

``folder_entries`` takes the order and the times from the first of: a TUM ``rgb.txt`` in the folder
(``<seconds> <file>`` per line, ``#`` comments), a KITTI ``times.txt`` (seconds per line, one per
image) in the folder or its parent, file names that are decimal seconds (TUM's ``<timestamp>.png``);
else the image files sorted by name, with no times. Times written as decimal seconds are taken
exactly (``seconds_to_ns``). ``read_image`` reads one image as OpenCV does. Pure: files in, arrays out.
"""

from __future__ import annotations

import re
from decimal import ROUND_HALF_EVEN, Decimal, InvalidOperation
from pathlib import Path

import cv2
import numpy as np

__all__ = ["IMAGE_SUFFIXES", "ImageFolderError", "folder_entries", "is_image", "read_image", "seconds_to_ns"]

IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".ppm", ".pgm", ".webp"}


class ImageFolderError(ValueError):
    """A folder's list of times that cannot be read; the message names the list and the line."""


def read_image(path: Path) -> np.ndarray | None:
    """The image file ``path`` as (H, W) or (H, W, 3|4) uint8 or uint16, as OpenCV reads it (a single channel
    made (H, W)); None when it cannot be read or is of another depth or layout."""
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None or image.dtype not in (np.uint8, np.uint16) or image.ndim not in (2, 3):
        return None
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    return image


def is_image(path: Path) -> bool:
    """Whether ``path`` is a file with an image suffix (``IMAGE_SUFFIXES``, any case)."""
    return path.suffix.lower() in IMAGE_SUFFIXES and path.is_file()


def seconds_to_ns(text: str) -> int:
    """Decimal seconds as written (``1341847980.722988``, ``1.036e-01``) -> int nanoseconds, exactly:
    decimal arithmetic, no float on the way, rounded half to even below the nanosecond.
    ValueError for text that is not a finite decimal number."""
    try:
        seconds = Decimal(text.strip())
    except InvalidOperation:
        raise ValueError(f"{text!r} is not a time in seconds") from None
    if not seconds.is_finite():
        raise ValueError(f"{text!r} is not a time in seconds")
    return int((seconds * 1_000_000_000).to_integral_value(rounding=ROUND_HALF_EVEN))


def folder_entries(folder: Path) -> list[tuple[Path, int | None]]:
    """``(file, time_ns)`` per image of ``folder``, in order (see the module docstring); time_ns None when the
    folder says no times. Raises ImageFolderError naming the list and the line when a time there is not a number."""
    listing = folder / "rgb.txt"
    if listing.is_file():
        entries: list[tuple[Path, int | None]] = []
        for number, line in enumerate(listing.read_text().splitlines(), 1):
            parts = line.split()
            if len(parts) >= 2 and not line.lstrip().startswith("#"):
                entries.append((folder / parts[1], _listed_time(parts[0], listing, number)))
        return entries
    files = sorted(p for p in folder.iterdir() if is_image(p))
    for times in (folder / "times.txt", folder.parent / "times.txt"):
        if times.is_file():
            values = [_listed_time(v, times, n) for n, v in enumerate(times.read_text().split(), 1)]
            if len(values) == len(files):
                return list(zip(files, values, strict=True))
    if files and all(re.fullmatch(r"\d+\.\d+", p.stem) for p in files):
        stamped = sorted((seconds_to_ns(p.stem), p) for p in files)
        return [(p, time_ns) for time_ns, p in stamped]
    return [(p, None) for p in files]


def _listed_time(text: str, listing: Path, number: int) -> int:
    try:
        return seconds_to_ns(text)
    except ValueError as exc:
        raise ImageFolderError(f"{listing}: entry {number}: {exc}") from None
