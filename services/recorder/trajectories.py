"""Trajectories from files: TUM, KITTI pose files and pose keys of artrack recordings.

* TUM (``stamp tx ty tz qx qy qz qw``): one pose ``T_world_body`` per line, stamp in seconds
  (read exactly, to the nanosecond), quaternion x y z w (normalised; one whose norm is more than
  ``QUATERNION_NORM_TOLERANCE`` from 1 is refused). Lines starting with ``#`` and blank lines
  are skipped; commas and tabs separate as well as spaces.
  A TUM file has no frame numbers (``frames`` is None).
* KITTI (12 numbers a line): the row-major 3x4 ``[R | t]`` of ``T_world_body``; the line's index
  among the poses is its frame number (``frames`` 0..N-1). Stamps come from KITTI's
  ``times.txt`` (seconds, one a line) when one lies beside the pose file with a line per pose;
  else ``stamps_ns`` is None.
* MCAP: the poses of one key, decoded as ``artrack export --format tum`` decodes them (``Pose``
  messages in a state with an estimate; ``GroundTruth`` messages need the child frame), with
  both stamps (``header.stamp_ns``) and frame numbers (``header.seq``, the source's frames as
  sent, from 0: an ``images:`` folder's in file order, as KITTI's, while every file reads).

``load_trajectory`` tells them apart by content: the MCAP magic, else the column count of the
first pose line (a text format can be forced). ``pairing.pair`` pairs two trajectories row by row.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, replace
from decimal import Decimal, InvalidOperation
from pathlib import Path

import numpy as np

from services.geometry.se3 import from_quaternion_translation
from services.recorder.export import Export
from services.recorder.reading import MAGIC, Damage

__all__ = ["KITTI_TIMES", "TEXT_FORMATS", "Trajectory", "TrajectoryError", "is_recording", "load_trajectory",
           "read_kitti", "read_recording", "read_tum", "text_format"]

TEXT_FORMATS = ("tum", "kitti")
log = logging.getLogger(__name__)
QUATERNION_NORM_TOLERANCE = 1e-2
ROTATION_TOLERANCE = 1e-3
"""Largest entry of ``R^T R - I`` accepted from a KITTI line."""
NS_PER_S = 1_000_000_000
KITTI_TIMES = "times.txt"
"""KITTI's stamps file (seconds from the sequence's start, one line per frame), read beside a KITTI pose file."""


class TrajectoryError(ValueError):
    """A trajectory file that cannot be read, naming the file (and line) and why."""


@dataclass(frozen=True)
class Trajectory:
    """(N, 4, 4) float64 ``T_world_body`` poses with (N,) int64 stamps in nanoseconds, or None when the
    source has no stamps (a KITTI file without ``times.txt``), and (N,) int64 frame numbers, or None
    when it has none (TUM). ``name`` says where it came from; ``damage`` where the damaged recording it was
    read from stops (its intact part was read), None for an intact file."""

    poses: np.ndarray
    stamps_ns: np.ndarray | None
    name: str
    frames: np.ndarray | None = None
    damage: Damage | None = None

    def __len__(self) -> int:
        return len(self.poses)


def _rows(path: Path) -> list[tuple[int, list[str]]]:
    """(line number, fields) of each line of ``path`` that is not blank or a comment."""
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise TrajectoryError(f"cannot read {path}: {getattr(exc, 'strerror', None) or exc}") from exc
    rows = []
    for number, line in enumerate(text.splitlines(), start=1):
        line = line.strip()
        if line and not line.startswith("#"):
            rows.append((number, line.replace(",", " ").split()))
    return rows


def _numbers(path: Path, number: int, fields: list[str], count: int, what: str) -> list[float]:
    if len(fields) != count:
        raise TrajectoryError(f"{path}:{number}: {what} needs {count} numbers a line, found {len(fields)}")
    try:
        values = [float(field) for field in fields]
    except ValueError as exc:
        raise TrajectoryError(f"{path}:{number}: not a number: {exc.args[0].split(': ', 1)[-1]}") from exc
    if not all(math.isfinite(v) for v in values):
        raise TrajectoryError(f"{path}:{number}: numbers must be finite")
    return values


def _stamp_ns(path: Path, number: int, text: str) -> int:
    """Decimal seconds ``text`` (line ``number`` of ``path``) as int nanoseconds, exactly."""
    try:
        seconds = Decimal(text)
    except InvalidOperation as exc:
        raise TrajectoryError(f"{path}:{number}: stamp {text!r} is not a number of seconds") from exc
    if not seconds.is_finite():
        raise TrajectoryError(f"{path}:{number}: stamp {text!r} is not a number of seconds")
    return int((seconds * NS_PER_S).to_integral_value())


def read_tum(path: Path | str) -> Trajectory:
    """The poses and stamps of a TUM trajectory file."""
    path = Path(path)
    poses, stamps = [], []
    for number, fields in _rows(path):
        values = _numbers(path, number, fields, 8, "a TUM file (stamp tx ty tz qx qy qz qw)")
        stamps.append(_stamp_ns(path, number, fields[0]))
        q = np.array(values[4:])
        norm = float(np.linalg.norm(q))
        if abs(norm - 1.0) > QUATERNION_NORM_TOLERANCE:
            raise TrajectoryError(f"{path}:{number}: quaternion (qx qy qz qw) has norm {norm:.6g}, not 1")
        poses.append(from_quaternion_translation(q / norm, np.array(values[1:4])))
    return _trajectory(path, poses, np.array(stamps, dtype=np.int64))


def read_kitti(path: Path | str) -> Trajectory:
    """The poses of a KITTI pose file, their frame numbers 0..N-1, and their stamps when ``times.txt``
    beside it has one line per pose (one with another count is left out, said in a warning)."""
    path = Path(path)
    poses = []
    for number, fields in _rows(path):
        T = np.eye(4)
        T[:3, :] = np.reshape(_numbers(path, number, fields, 12, "a KITTI pose file (row-major 3x4 [R|t])"), (3, 4))
        if np.max(np.abs(T[:3, :3].T @ T[:3, :3] - np.eye(3))) > ROTATION_TOLERANCE or np.linalg.det(T[:3, :3]) < 0:
            raise TrajectoryError(f"{path}:{number}: the 3x3 part is not a rotation")
        poses.append(T)
    trajectory = _trajectory(path, poses, _kitti_times(path.with_name(KITTI_TIMES), len(poses)))
    return replace(trajectory, frames=np.arange(len(trajectory), dtype=np.int64))


def _kitti_times(path: Path, count: int) -> np.ndarray | None:
    """(count,) int64 stamps (ns) of the KITTI ``times.txt`` at ``path``; None when there is none, or it
    holds another number of lines than ``count``."""
    if not path.is_file():
        return None
    rows = _rows(path)
    if len(rows) != count:
        log.warning("%s holds %d stamps for %d poses: not used", path, len(rows), count)
        return None
    for number, fields in rows:
        if len(fields) != 1:
            raise TrajectoryError(f"{path}:{number}: KITTI times need 1 number a line, found {len(fields)}")
    return np.array([_stamp_ns(path, number, fields[0]) for number, fields in rows], dtype=np.int64)


def read_recording(path: Path | str, key: str | None, child: str | None = None) -> Trajectory:
    """The poses of one key of an artrack recording (as ``artrack export --format tum`` reads them), their
    stamps and frame numbers the source stamps and sequence numbers of the frames they were estimated from."""
    path = Path(path)
    if not key:
        raise TrajectoryError(f"{path} is a recording: name the pose key to read (--est-key / --gt-key)")
    job = Export(path, key, "tum", child=child)
    stamped = list(job.transforms())
    poses = [from_quaternion_translation(np.array(t.rotation), np.array(t.translation)) for _, t in stamped]
    name = f"{path} {key}" + (f" ({child})" if child else "")
    trajectory = _trajectory(name, poses, np.array([header.stamp_ns for header, _ in stamped], dtype=np.int64))
    return replace(trajectory, frames=np.array([header.seq for header, _ in stamped], dtype=np.int64),
                   damage=job.damage)


def _trajectory(name: Path | str, poses: list[np.ndarray], stamps: np.ndarray | None) -> Trajectory:
    if not poses:
        raise TrajectoryError(f"{name} holds no poses")
    return Trajectory(np.array(poses), stamps, str(name))


def is_recording(path: Path | str) -> bool:
    """Whether ``path`` starts with the MCAP magic."""
    try:
        with open(path, "rb") as file:
            return file.read(len(MAGIC)) == MAGIC
    except OSError as exc:
        raise TrajectoryError(f"cannot read {path}: {exc.strerror or exc}") from exc


def text_format(path: Path | str) -> str:
    """``tum`` or ``kitti`` from the column count (8 or 12) of the first pose line of a text file."""
    path = Path(path)
    rows = _rows(path)
    if not rows:
        raise TrajectoryError(f"{path} holds no poses")
    number, fields = rows[0]
    columns = {8: "tum", 12: "kitti"}
    if len(fields) not in columns:
        raise TrajectoryError(f"{path}:{number}: {len(fields)} columns: neither TUM (8) nor KITTI (12)")
    return columns[len(fields)]


def load_trajectory(path: Path | str, fmt: str | None = None, *, key: str | None = None,
                    child: str | None = None) -> Trajectory:
    """A trajectory from an MCAP recording (its pose ``key``, GroundTruth's ``child``) or a text file read
    as ``fmt`` (``tum`` or ``kitti``; None: told apart by ``text_format``)."""
    if fmt is not None and fmt not in TEXT_FORMATS:
        raise TrajectoryError(f"unknown trajectory format {fmt!r} (use {', '.join(TEXT_FORMATS)})")
    if is_recording(path):
        return read_recording(path, key, child)
    return read_tum(path) if (fmt or text_format(path)) == "tum" else read_kitti(path)
