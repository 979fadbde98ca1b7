"""Looking at a running system: which nodes are up, and what flows on a key."""

from __future__ import annotations

import json
import sys
import time
from collections.abc import Iterator
from typing import TextIO

import zenoh

from protocol.codec import DecodeError, sample_record
from protocol.keys import Keys
from protocol.message import Message
from protocol.system import NodeStats
from services.bus.discovery import live_nodes
from services.bus.pubsub import Inbox, Received, Role


def _ms(value: float | None) -> str:
    return "-" if value is None else f"{value:.2f}"


def format_nodes(nodes: list[tuple[str, str]], states: list[tuple[tuple[str, str], NodeStats]]) -> str:
    """A table of the nodes holding a token, one row per process answering for each (two processes
    under one name give two rows; a node that did not answer its state query has one row of ``-``),
    with their health figures (UNJOINED: messages of synced inputs that joined no set)."""
    header = ("RIG", "NODE", "KIND", "PID", "UP(s)", "IN", "OUT", "DROPPED", "UNJOINED", "DECODE_ERR", "P50(ms)",
              "P99(ms)", "LAT50(ms)", "LAT99(ms)")
    rows: list[tuple[str, ...]] = [header]
    for rig, name in sorted(set(nodes) | {node for node, _ in states}):
        answered = sorted((s for node, s in states if node == (rig, name)), key=lambda s: (s.host, s.pid))
        if not answered:
            rows.append((rig, name, "?", *("-",) * (len(header) - 3)))
        for s in answered:
            rows.append((rig, name, s.kind, str(s.pid), f"{s.uptime_s:.0f}", str(s.received), str(s.published),
                         str(s.dropped), str(s.unjoined), str(s.decode_errors), _ms(s.processing_ms_p50),
                         _ms(s.processing_ms_p99), _ms(s.latency_ms_p50), _ms(s.latency_ms_p99)))
    return format_table(rows)


def format_table(rows: list[tuple[str, ...]]) -> str:
    """Rows of cells as left-aligned columns two spaces apart (the first row is the header)."""
    widths = [max(len(row[i]) for row in rows) for i in range(len(rows[0]))]
    return "\n".join("  ".join(cell.ljust(w) for cell, w in zip(row, widths, strict=True)).rstrip() for row in rows)


def echo(session: zenoh.Session, key: str, *, count: int = 0, timeout_s: float | None = None,
         max_array_elements: int | None = 16) -> Iterator[dict]:
    """Decoded messages on ``key`` as JSON-ready dicts (``sample_record``: ``key`` is the key each one
    arrived on, whatever its own fields say), in order.

    Undecodable payloads yield ``{"key", "error"}``. Stops after ``count`` messages (0 = no
    limit) or when nothing arrives for ``timeout_s``.
    """
    errors: list[tuple[str, DecodeError]] = []
    inbox: Inbox[Message] = Inbox(session, key, None, Role.RESULT, on_decode_error=lambda k, e: errors.append((k, e)))
    seen = 0
    idle_since = time.monotonic()
    try:
        while count == 0 or seen < count:
            received: Received | None = inbox.recv(0.2)
            while errors:
                bad_key, error = errors.pop(0)
                idle_since = time.monotonic()
                yield {"key": bad_key, "error": str(error)}
            if received is None:
                if timeout_s is not None and time.monotonic() - idle_since > timeout_s:
                    return
                continue
            idle_since = time.monotonic()
            seen += 1
            yield sample_record(received.key, received.received_ns, received.message, max_array_elements)
    finally:
        inbox.close()


def print_json_lines(records: Iterator[dict], out: TextIO = sys.stdout) -> int:
    """Write each record as one JSON line, flushing as they come; return how many."""
    n = 0
    for record in records:
        out.write(json.dumps(record) + "\n")
        out.flush()
        n += 1
    return n


def wait_for_nodes(session: zenoh.Session, keys: Keys, names: set[str], timeout_s: float) -> set[str]:
    """Wait until every node in ``names`` (of this rig) is live; return those that are."""
    deadline = time.monotonic() + timeout_s
    while True:
        live = {name for rig, name in live_nodes(session, keys, 0.3) if rig == keys.rig}
        if names <= live or time.monotonic() > deadline:
            return live & names
        time.sleep(0.1)
