"""One key of a recording as a TUM trajectory, CSV or JSON lines.

* ``tum``: one line per pose, ``stamp tx ty tz qx qy qz qw`` (the format evo and the SLAM
  benchmarks read): stamp = ``header.stamp_ns`` in seconds, written exactly (9 decimals);
  translation in metres, rotation quaternion x y z w, as Python's shortest round-trip
  numbers. ``Pose`` messages give ``T_<frame_id>_<child_frame_id>`` (``child`` keeps one
  child frame); ``GroundTruth`` messages give their transform whose child frame is
  ``child``, which must then be named.
* ``csv``: a header row, then one row per message: ``received_ns`` (the log time), then the
  message's fields flattened (``header.stamp_ns``, ``transform.translation.0``, ...). The
  columns are every field any message had, in first-seen order (the file is read twice).
* ``jsonl``: one JSON object per message, as ``artrack echo`` prints them: ``key`` (the key it
  was recorded on), ``received_ns``, ``schema``, ``version`` and the fields (a field named
  ``key`` as ``message_key``: ``protocol.codec.sample_record``).

In CSV and JSON lines, arrays of more than 16 elements are summarised as dtype and shape
unless ``full``. Messages that do not decode are skipped and counted.

A key expression (``*``, ``**``, ``$*``: ``ar/rig0/pose/cam0/**``) exports every recorded key
it matches (Zenoh's matching, ``matching_keys``), each into its own file named after the key
(``export_path``).
"""

from __future__ import annotations

import csv
import io
import json
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any

import zenoh

from protocol.codec import DecodeError, decode, sample_record, to_json
from protocol.keys import check_expression
from protocol.maps import Trajectory
from protocol.message import Header, Message
from protocol.poses import GroundTruth, Pose
from protocol.spatial import Transform
from protocol.tracking_state import TrackingState
from services.convert import transform_from_matrix
from services.recorder.info import summarise
from services.recorder.reading import Damage, Scan
from services.recorder.writing import RECORDING_METADATA

FORMATS = ("tum", "csv", "jsonl")
SUMMARISE_OVER = 16
ESTIMATED = frozenset({TrackingState.TRACKING, TrackingState.RECOGNISED})
"""Pose states a trajectory is made of: a fresh estimate from the frame's own measurements, followed
on or recognised afresh (a
``predicted`` pose is carried over, no measurement of its own, and would weigh twice in ATE/RPE)."""


class ExportError(ValueError):
    """The key, format or child frame asked for does not fit the recording."""


def tum_line(stamp_ns: int, transform: Transform) -> str:
    """``stamp tx ty tz qx qy qz qw`` with the stamp in seconds, exact to the nanosecond."""
    return " ".join([f"{stamp_ns // 1_000_000_000}.{stamp_ns % 1_000_000_000:09d}",
                     *map(repr, transform.translation), *map(repr, transform.rotation)])


def is_expression(key: str) -> bool:
    """True when ``key`` has wildcards (``*``, ``**``, ``$*``), so it may match several keys."""
    return "*" in key


def matching_keys(path: Path | str, expression: str) -> tuple[list[str], str]:
    """``(keys, prefix)``: the recorded keys ``expression`` matches, sorted, and the recording's
    ``namespace/rig`` (empty when it does not say). The expression is absolute or relative to that
    prefix. Raises ValueError for an expression that is not valid, ExportError when nothing matches
    (naming the keys there are)."""
    check_expression(expression)
    info = summarise(path)
    recording = info.metadata.get(RECORDING_METADATA, {})
    prefix = f"{recording['namespace']}/{recording['rig']}" if "namespace" in recording and "rig" in recording else ""
    wanted = [zenoh.KeyExpr(expression)] + ([zenoh.KeyExpr(f"{prefix}/{expression}")] if prefix else [])
    recorded = sorted({channel.key for channel in info.channels})
    keys = [key for key in recorded if any(w.intersects(zenoh.KeyExpr(key)) for w in wanted)]
    if not keys:
        raise ExportError(f"no key matches {expression!r} in {path} (keys: {', '.join(recorded) or 'none'})")
    return keys, prefix


def export_path(folder: Path, key: str, prefix: str, fmt: str) -> Path:
    """Where the export of ``key`` goes: ``folder/<key relative to prefix>.<fmt>``, the key's segments
    as folders (``pose/cam0/marker/3.tum``): every key its own file, named after it."""
    *parents, last = (key.removeprefix(f"{prefix}/") if prefix else key).split("/")
    return folder.joinpath(*parents, f"{last}.{fmt}")


def flatten(value: Any, prefix: str = "") -> dict[str, Any]:
    """Nested dicts and lists as one level: ``{"a": {"b": [1, 2]}}`` -> ``{"a.b.0": 1, "a.b.1": 2}``."""
    items: Iterable[tuple[object, Any]]
    if isinstance(value, dict):
        items = value.items()
    elif isinstance(value, list | tuple):
        items = enumerate(value)
    else:
        return {prefix: value}
    flat: dict[str, Any] = {}
    for name, item in items:
        flat.update(flatten(item, f"{prefix}.{name}" if prefix else str(name)))
    return flat


class Export:
    """The lines of one export; iterate ``lines()`` once, then read ``rows``, ``skipped``, ``damage``.

    ``key`` is a recorded key, absolute or relative to the recording's ``namespace/rig``.
    ``lines()`` raises ``ExportError`` when no channel has the key (naming the keys there
    are) or when the format does not fit its messages.
    """

    def __init__(self, path: Path | str, key: str, fmt: str, *, child: str | None = None, full: bool = False):
        if fmt not in FORMATS:
            raise ExportError(f"unknown format {fmt!r} (use {', '.join(FORMATS)})")
        self.path, self.key, self.format, self.child = Path(path), key, fmt, child
        self.max_elements = None if full else SUMMARISE_OVER
        self.rows = 0
        self.skipped = 0
        self.damage: Damage | None = None
        Scan(self.path)  # fail now on a file that is not MCAP

    def lines(self) -> Iterator[str]:
        """Output lines, without line ends."""
        if self.format == "tum":
            yield from self._tum()
        elif self.format == "jsonl":
            for topic, log_time, message in self.messages():
                self.rows += 1
                yield json.dumps(sample_record(topic, log_time, message, self.max_elements))
        else:
            yield from self._csv()

    def messages(self) -> Iterator[tuple[str, int, Message]]:
        """(key, log time, decoded message) of every message on the key, in file order."""
        scan = Scan(self.path)
        wanted, seen = {self.key}, set()
        self.skipped = 0
        for recorded in scan.messages():
            recording = scan.metadata.get(RECORDING_METADATA, {})
            if "namespace" in recording and "rig" in recording:
                wanted.add(f"{recording['namespace']}/{recording['rig']}/{self.key}")
            topic = recorded.channel.topic
            seen.add(topic)
            if topic not in wanted:
                continue
            try:
                message = decode(recorded.message.data)
            except DecodeError:
                self.skipped += 1
                continue
            yield topic, recorded.message.log_time, message
        self.damage = scan.damage
        if not seen & wanted:
            raise ExportError(f"no key {self.key!r} in {self.path} (keys: {', '.join(sorted(seen)) or 'none'})")

    def transforms(self) -> Iterator[tuple[Header, Transform]]:
        """``(header, transform)`` of every estimated pose on the key, as ``tum`` writes them (its stamp
        ``header.stamp_ns``; ``header.seq`` the frame's sequence number, which TUM has no column for).

        ``Pose`` messages in a state other than ``tracking`` are left out: lost, initialising and
        no calibration carry a placeholder transform, predicted one carried over from an earlier
        frame; neither is a measurement of this frame. A ``Trajectory`` key gives the rows of its last
        message (each holds the whole trajectory of its map), after the poses of any other message.
        Raises ``ExportError`` as ``lines()``.
        """
        final: Trajectory | None = None
        for _, _, message in self.messages():
            if isinstance(message, Trajectory):
                final = message
                continue
            if isinstance(message, Pose):
                if self.child is not None and message.child_frame_id != self.child:
                    continue
                if message.state not in ESTIMATED:
                    continue
                transforms = [message.transform]
            elif isinstance(message, GroundTruth):
                children = [t.child_frame for t in message.transforms]
                if self.child is None:
                    raise ExportError(f"{self.key} carries GroundTruth: choose a child frame with --child "
                                      f"(this message has {', '.join(children) or 'none'})")
                transforms = [t.transform for t in message.transforms if t.child_frame == self.child]
            else:
                raise ExportError(f"tum needs Pose, GroundTruth or Trajectory messages; {self.key} carries "
                                  f"{message.SCHEMA}")
            for transform in transforms:
                yield message.header, transform
        if final is not None:
            for stamp, seq, T in zip(final.stamps_ns.tolist(), final.seqs.tolist(), final.poses, strict=True):
                yield (final.header.model_copy(update={"stamp_ns": stamp, "seq": seq}),
                       transform_from_matrix(T))

    def _tum(self) -> Iterator[str]:
        for header, transform in self.transforms():
            self.rows += 1
            yield tum_line(header.stamp_ns, transform)

    def _csv(self) -> Iterator[str]:
        def rows() -> Iterator[dict[str, Any]]:
            for _, log_time, message in self.messages():
                yield {"received_ns": log_time, **flatten(to_json(message, self.max_elements))}

        columns: dict[str, None] = {}
        for row in rows():
            columns.update(dict.fromkeys(row))
        buffer = io.StringIO()
        writer = csv.DictWriter(buffer, fieldnames=list(columns), lineterminator="")

        def line(write: Callable[..., object], *args: Any) -> str:
            buffer.seek(0)
            buffer.truncate()
            write(*args)
            return buffer.getvalue()

        yield line(writer.writeheader)
        for row in rows():
            self.rows += 1
            yield line(writer.writerow, row)
