"""One run of one variant: a paced latency phase, then a flood throughput phase.

* Latency: ``WARMUP + LATENCY_N`` messages at ``RATE_HZ`` (unless the caller says otherwise);
  the warm-up messages (Zenoh's shared-memory pool and Python's caches settle during them) are
  left out; p50 and p99 of the one-way latencies the sink measured.
* Throughput: the bench process puts messages back to back for ``FLOOD_S`` with
  ``CongestionControl.BLOCK``, so nothing may be dropped; the sink counts them.
  msg/s = (received - 1) / (last arrival - first arrival), valid only with ``lost == 0``.

Each phase publishes on a key of its own, so nothing left over from one phase reaches the next.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from services.bus.pubsub import Role
from tests.bench.link import BenchError, Sink
from tests.bench.traffic import Sender, SenderFactory

WARMUP = 20
LATENCY_N = 300
RATE_HZ = 100.0
FLOOD_S = 1.5
MATCH_S = 5.0
SETTLE_S = 0.2


@dataclass(frozen=True)
class Run:
    """The figures of one run."""

    msg_per_s: float
    latency_p50_us: float
    latency_p99_us: float
    latency_n: int
    flood_sent: int
    lost: int


def measure(sink: Sink, key: str, reader: dict[str, Any], make_sender: SenderFactory,
            paced_role: Role, flood_role: Role, *, rate_hz: float = RATE_HZ, latency_n: int = LATENCY_N) -> Run:
    """Run both phases of one variant on keys under ``key``: ``latency_n`` timed messages at ``rate_hz``."""
    _, paced = _phase(sink, f"{key}/paced", reader, make_sender, paced_role,
                      lambda sender: _paced(sender, WARMUP + latency_n, rate_hz))
    latencies = paced["latencies_us"][WARMUP:]
    sent, flood = _phase(sink, f"{key}/flood", reader, make_sender, flood_role,
                         lambda sender: _flood(sender, FLOOD_S))
    received = flood["received"]
    if not latencies or received < 2:
        raise BenchError(f"{key}: too little arrived ({paced['received']} paced, {received} of {sent} flooded)")
    p50, p99 = np.percentile(latencies, [50, 99])
    return Run(msg_per_s=(received - 1) / ((flood["last_ns"] - flood["first_ns"]) / 1e9),
               latency_p50_us=float(p50), latency_p99_us=float(p99), latency_n=len(latencies),
               flood_sent=sent, lost=sent - received)


def _phase(sink: Sink, key: str, reader: dict[str, Any], make_sender: SenderFactory, role: Role,
           drive: Callable[[Sender], int]) -> tuple[int, dict[str, Any]]:
    """Subscribe the sink to ``key``, publish with ``drive`` (returns how many it sent), collect."""
    assert sink.session is not None
    sink.start(key, reader)
    sender = make_sender(sink.session, key, role)
    try:
        deadline = time.monotonic() + MATCH_S
        while not sender.matched():
            if time.monotonic() > deadline:
                raise BenchError(f"no subscriber matched {key} within {MATCH_S:.0f} s")
            time.sleep(0.01)
        time.sleep(SETTLE_S)
        sent = drive(sender)
        return sent, sink.stop(sent)
    finally:
        sender.close()


def _paced(sender: Sender, count: int, rate_hz: float) -> int:
    """Send ``count`` messages on a fixed schedule (sleeping, never spinning: the sink needs the CPU)."""
    due = time.perf_counter()
    for seq in range(count):
        sender.send(seq)
        due += 1.0 / rate_hz
        time.sleep(max(0.0, due - time.perf_counter()))
    return count


def _flood(sender: Sender, seconds: float) -> int:
    """Send back to back for ``seconds``; return how many went out."""
    deadline = time.perf_counter() + seconds
    seq = 0
    while time.perf_counter() < deadline:
        sender.send(seq)
        seq += 1
    return seq
