"""A target library: a folder holding one file per target, plus a copy of each target's image.

``<name>.npz`` (numpy's zip of arrays, read without pickle) holds ``header``, the UTF-8 bytes of a
JSON object, and the arrays ``keypoints`` (N, 2) float32 image pixels, ``levels`` (N,) uint8,
``descriptors`` (N, D) uint8 or float32 and ``points`` (N, 3) float64 target frame (see
``services.estimation.targets.target``). The header::

    {"format": "artrack-target", "version": 2, "name": "poster",
     "detector": {"method": "orb", "descriptor": "native", "max_count": 2000, ...},
     "width_m": 0.297, "image_size": [1024, 724], "image": "poster.png", "source": "/path/poster.jpg"}

``detector`` holds every field of the ``KeypointParams`` that found the keypoints, so frames are
described alike. Version 1 files (a feature name instead of the settings) are refused: the target
is added again from its image.

``<name>.png`` is the target's grey image. Files are written to a temporary name and renamed, so
a library never holds half a target. The default folder is ``$XDG_DATA_HOME/artrack/targets``,
else ``~/.local/share/artrack/targets``.

Every refusal is a ``TargetLibraryError`` (a ValueError) with a one-line message: an image that
is missing or unreadable, a width that is not a positive number, a name that is taken or
malformed, an unknown name, or a damaged target file (naming the file and what is wrong).
"""

from __future__ import annotations

import json
import math
import os
import re
import zipfile
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from pydantic import ValidationError

from services.detection.keypoints.detector import KeypointDetector, KeypointParams
from services.estimation.targets.features import DEFAULT_FEATURE, Extractor
from services.estimation.targets.target import Target, build_target, check_width, target_points

__all__ = [
    "FORMAT",
    "NAME_PATTERN",
    "VERSION",
    "DamagedTargetError",
    "DuplicateTargetError",
    "TargetImageError",
    "TargetInfo",
    "TargetLibrary",
    "TargetLibraryError",
    "UnknownTargetError",
    "default_library_dir",
    "read_target",
    "write_target",
]

FORMAT = "artrack-target"
VERSION = 2
NAME_PATTERN = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]{0,63}")
"""Target names: a file stem and one key-expression chunk (a pose is published under the name)."""
SUFFIX = ".npz"
ARRAYS = {"keypoints": (2, "float32"), "levels": (1, "uint8"), "points": (2, "float64")}
"""Arrays of a target file besides ``descriptors``: name -> (ndim, dtype)."""


class TargetLibraryError(ValueError):
    """A target or library operation that cannot be done; the message says what and why on one line."""


class TargetImageError(TargetLibraryError):
    """The image is missing or unreadable."""


class DuplicateTargetError(TargetLibraryError):
    """The library already holds a target of that name."""


class UnknownTargetError(TargetLibraryError):
    """The library holds no target of that name."""


class DamagedTargetError(TargetLibraryError):
    """A target file that cannot be read back; the message names the file and why."""


@dataclass(frozen=True)
class TargetInfo:
    """A target's header: ``name``, ``feature``, ``width_m`` and ``height_m`` (metres), ``image_size``
    (width, height) pixels, ``keypoints`` count, ``source`` (the image it was built from) and ``path``;
    ``detector``: the settings that found the keypoints; ``per_level``: keypoints of each pyramid level,
    finest first; ``descriptor``: what describes them, e.g. ``ORB, 32 bytes, hamming``."""

    name: str
    feature: str
    width_m: float
    height_m: float
    image_size: tuple[int, int]
    keypoints: int
    source: str
    path: Path
    detector: KeypointParams
    per_level: tuple[int, ...]
    descriptor: str


def default_library_dir() -> Path:
    """``$XDG_DATA_HOME/artrack/targets``, else ``~/.local/share/artrack/targets``."""
    base = os.environ.get("XDG_DATA_HOME") or str(Path.home() / ".local" / "share")
    return Path(base) / "artrack" / "targets"


def check_name(name: str) -> str:
    """``name`` when it matches ``NAME_PATTERN``; TargetLibraryError otherwise."""
    if not isinstance(name, str) or not NAME_PATTERN.fullmatch(name):
        raise TargetLibraryError(f"target name {name!r}: use 1 to 64 letters, digits, '_', '.' or '-', "
                                 "not starting with '.' or '-'")
    return name


def read_image(path: Path) -> np.ndarray:
    """The image file at ``path`` as OpenCV reads it (any depth, grey or BGR); TargetImageError when it is
    missing or unreadable."""
    if not path.is_file():
        raise TargetImageError(f"target image {path}: no such file")
    image = cv2.imread(str(path), cv2.IMREAD_ANYDEPTH | cv2.IMREAD_ANYCOLOR)
    if image is None:
        raise TargetImageError(f"target image {path}: not an image OpenCV can read")
    return image


def write_target(target: Target, path: Path, source: str = "") -> None:
    """Write ``target`` to ``path`` (``<name>.npz``) and its image beside it (``<name>.png``), each through
    a temporary file renamed into place."""
    image_path = path.with_suffix(".png")
    header = {"format": FORMAT, "version": VERSION, "name": target.name, "detector": target.detector.model_dump(),
              "width_m": target.width_m, "image_size": list(target.size_px), "image": image_path.name,
              "source": source}
    partial_image = image_path.with_name(f".{image_path.name}.partial.png")
    if not cv2.imwrite(str(partial_image), target.image):
        raise TargetLibraryError(f"cannot write {image_path}")
    os.replace(partial_image, image_path)
    partial = path.with_name(f".{path.name}.partial{SUFFIX}")
    with open(partial, "wb") as file:
        np.savez(file, header=np.frombuffer(json.dumps(header).encode(), np.uint8), keypoints=target.keypoints,
                 levels=target.levels, descriptors=target.descriptors, points=target.points)
    os.replace(partial, path)


def read_header(path: Path, arrays: dict[str, np.ndarray]) -> dict:
    """The checked JSON header of a target file's ``arrays``; DamagedTargetError naming ``path`` otherwise."""
    if "header" not in arrays:
        raise DamagedTargetError(f"target file {path}: no header")
    try:
        header = json.loads(arrays["header"].tobytes().decode())
    except (UnicodeDecodeError, json.JSONDecodeError) as error:
        raise DamagedTargetError(f"target file {path}: header is not JSON ({error})") from error
    if not isinstance(header, dict) or header.get("format") != FORMAT:
        raise DamagedTargetError(f"target file {path}: not an {FORMAT} file")
    if header.get("version") != VERSION:
        raise DamagedTargetError(f"target file {path}: format version {header.get('version')!r}, this "
                                 f"version reads {VERSION}: add the target again from its image")
    width_m, size = header.get("width_m"), header.get("image_size")
    if not (isinstance(width_m, (int, float)) and math.isfinite(width_m) and width_m > 0):
        raise DamagedTargetError(f"target file {path}: width_m {width_m!r} is not a positive number")
    if not (isinstance(size, list) and len(size) == 2 and all(isinstance(v, int) and v > 0 for v in size)):
        raise DamagedTargetError(f"target file {path}: image_size {size!r} is not [width, height] pixels")
    for key in ("name", "image", "source"):
        if not isinstance(header.get(key), str):
            raise DamagedTargetError(f"target file {path}: header has no {key}")
    if Path(header["image"]).name != header["image"]:
        raise DamagedTargetError(f"target file {path}: image {header['image']!r} is not a file beside it")
    header["detector"] = read_detector(path, header.get("detector"))
    return header


def read_detector(path: Path, settings: object) -> KeypointParams:
    """The detector settings of a header's ``detector`` object; DamagedTargetError naming ``path`` otherwise."""
    if not isinstance(settings, dict):
        raise DamagedTargetError(f"target file {path}: header has no detector settings")
    try:
        return KeypointParams.model_validate(settings)
    except ValidationError as error:
        problems = "; ".join(f"{'.'.join(map(str, p['loc']))}: {p['msg']}" for p in error.errors())
        raise DamagedTargetError(f"target file {path}: detector settings {settings!r}: {problems}") from error


def read_target(path: str | Path) -> Target:
    """The target stored at ``path`` (a ``.npz`` target file with its image beside it); DamagedTargetError
    naming the file and the fault when it cannot be read back whole."""
    return read_target_file(Path(path))[0]


def read_target_file(path: Path) -> tuple[Target, dict]:
    """``(target, header)`` of the target file ``path`` (as ``read_target``)."""
    try:
        with np.load(path, allow_pickle=False) as archive:
            arrays = {key: archive[key] for key in archive.files}
    except FileNotFoundError as error:
        raise UnknownTargetError(f"target file {path}: no such file") from error
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as error:
        raise DamagedTargetError(f"target file {path}: unreadable ({error})") from error
    header = read_header(path, arrays)
    descriptors = arrays.get("descriptors")
    try:
        expected = KeypointDetector(header["detector"]).empty().descriptors
    except ValueError as error:
        raise DamagedTargetError(f"target file {path}: {error}") from error
    if descriptors is None or descriptors.ndim != 2 or descriptors.dtype != expected.dtype \
            or descriptors.shape[1] != expected.shape[1]:
        raise DamagedTargetError(f"target file {path}: descriptors missing or not (N, {expected.shape[1]}) "
                                 f"{expected.dtype} as its detector gives")
    count = len(descriptors)
    for key, (ndim, dtype) in ARRAYS.items():
        array = arrays.get(key)
        if array is None or array.ndim != ndim or array.dtype != dtype or len(array) != count:
            raise DamagedTargetError(f"target file {path}: {key} missing or not {count} rows of {dtype}")
    if arrays["keypoints"].shape[1] != 2 or arrays["points"].shape[1] != 3:
        raise DamagedTargetError(f"target file {path}: keypoints must be (N, 2) and points (N, 3)")
    image_path = path.with_name(header["image"])
    image = cv2.imread(str(image_path), cv2.IMREAD_GRAYSCALE)
    if image is None:
        raise DamagedTargetError(f"target file {path}: its image {image_path.name} is missing or unreadable")
    size = tuple(header["image_size"])
    if (image.shape[1], image.shape[0]) != size:
        raise DamagedTargetError(f"target file {path}: image {image_path.name} is {image.shape[1]}x{image.shape[0]} "
                                 f"px, the header says {size[0]}x{size[1]}")
    if not np.allclose(target_points(arrays["keypoints"], (size[0], size[1]), header["width_m"]), arrays["points"]):
        raise DamagedTargetError(f"target file {path}: points do not lie where the keypoints and width put them")
    return Target(header["name"], image, float(header["width_m"]), header["detector"], arrays["keypoints"],
                  arrays["levels"], descriptors, arrays["points"]), header


class TargetLibrary:
    """The targets in ``folder`` (default ``default_library_dir()``; made when the first target is added)."""

    def __init__(self, folder: str | Path | None = None):
        self.folder = Path(folder) if folder is not None else default_library_dir()

    def path(self, name: str) -> Path:
        """The target file of ``name`` (which need not exist)."""
        return self.folder / f"{check_name(name)}{SUFFIX}"

    def existing(self, name: str) -> Path:
        """The target file of ``name``; UnknownTargetError naming the library's targets when absent."""
        path = self.path(name)
        if not path.is_file():
            known = ", ".join(self.names()) or "none"
            raise UnknownTargetError(f"no target {name!r} in {self.folder} (targets: {known})")
        return path

    def add(self, image_path: str | Path, width_m: float, name: str | None = None,
            feature: str | KeypointParams = DEFAULT_FEATURE, extract: Extractor | None = None,
            replace: bool = False) -> Target:
        """Build a target from the image file ``image_path`` printed ``width_m`` metres wide and store it as
        ``name`` (default: the file's stem); ``replace`` overwrites a target of that name."""
        image_path = Path(image_path)
        name = check_name(image_path.stem if name is None else name)
        path = self.path(name)
        if path.exists() and not replace:
            raise DuplicateTargetError(f"target {name!r} already exists in {self.folder} (remove it first)")
        try:
            width_m = check_width(width_m)
        except ValueError as error:
            raise TargetLibraryError(str(error)) from None
        try:
            target = build_target(name, read_image(image_path), width_m, feature, extract)
        except TargetLibraryError:
            raise
        except ValueError as error:
            raise TargetImageError(f"target image {image_path}: {error}") from error
        self.folder.mkdir(parents=True, exist_ok=True)
        write_target(target, path, str(image_path.resolve()))
        return target

    def names(self) -> list[str]:
        """Names of the stored targets, sorted."""
        if not self.folder.is_dir():
            return []
        return sorted(p.stem for p in self.folder.glob(f"*{SUFFIX}") if NAME_PATTERN.fullmatch(p.stem))

    def list(self) -> list[TargetInfo]:
        """The headers of the stored targets, sorted by name; DamagedTargetError on the first damaged file."""
        return [self.info(name) for name in self.names()]

    def info(self, name: str) -> TargetInfo:
        """What target ``name`` is (read and checked whole, as ``load``)."""
        target, header = read_target_file(self.existing(name))
        per_level = tuple(int(n) for n in np.bincount(target.levels))
        bits = target.descriptors.dtype == np.uint8
        size = f"{target.descriptors.shape[1]} {'bytes' if bits else 'floats'}"
        descriptor = f"{target.detector.descriptor_type}, {size}, {'hamming' if bits else 'l2'}"
        return TargetInfo(target.name, target.feature, target.width_m, target.height_m, target.size_px,
                          len(target.keypoints), header["source"], self.path(name), target.detector, per_level,
                          descriptor)

    def load(self, name: str) -> Target:
        """Target ``name``; UnknownTargetError when absent, DamagedTargetError when it cannot be read back."""
        return read_target(self.existing(name))

    def remove(self, name: str) -> None:
        """Delete target ``name`` and its image; UnknownTargetError when absent."""
        path = self.existing(name)
        path.unlink()
        path.with_suffix(".png").unlink(missing_ok=True)
