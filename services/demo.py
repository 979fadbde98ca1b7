"""``artrack demo``: a synthetic camera -> echo node -> this client, over Zenoh.

Starts the ``capture`` (test pattern) and ``echo`` nodes as separate processes, subscribes
to the echo output here, prints what flowed and a summary: frames, losses, end-to-end
latency from the frame's capture stamp to its arrival here (two process hops), and which
nodes were seen on the bus.
"""

from __future__ import annotations

import signal
import sys
import threading
import time
from typing import TextIO

import numpy as np

from protocol.sensors import Image
from services.launch import node_command
from services.observe import live_nodes
from services.runtime.bus import BusConfig, open_session
from services.runtime.pubsub import Inbox, Role
from services.runtime.supervisor import ProcessSpec, Supervisor

CAMERA = "cam0"
STARTUP_TIMEOUT_S = 30.0
QUIET_END_S = 2.0


def echo_depth(fps: float) -> int:
    """Frames the demo's echo node may queue: about two seconds' worth."""
    return max(1, min(1000, round(2 * fps)))


def run_demo(bus: BusConfig, frames: int, fps: float, out: TextIO = sys.stdout) -> int:
    """Run the demo; return 0 when every frame made it through, 1 otherwise."""
    keys = bus.keys
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    session = open_session(bus)
    supervisor = None
    try:
        inbox = Inbox(session, keys.echo(CAMERA), Image, Role.FRAME, depth=1024)
        env = bus.to_env()
        supervisor = Supervisor([
            ProcessSpec("cam", node_command("capture", "cam", {"cameras": [CAMERA], "frames": frames, "fps": fps,
                                                               "wait_for_subscriber": True}), env),
            # The demo counts every frame, so the relay queues ~2 s of frames instead of keeping only
            # the newest: a busy machine's scheduling stalls must not show up as losses.
            ProcessSpec("echo", node_command("echo", "echo", {"camera": CAMERA, "depth": echo_depth(fps)}), env),
        ])
        supervisor.start()
        print(f"demo: nodes 'cam' (capture, synthetic:pattern) and 'echo' on {keys.prefix}; "
              f"{frames} frames at {fps:g} fps. `artrack list` in another shell shows them.", file=out, flush=True)
        latencies, seqs, seen_nodes = [], [], set()
        started = last = time.monotonic()
        while len(seqs) < frames and not stop.is_set():
            supervisor.step()
            received = inbox.recv(0.1)
            now = time.monotonic()
            if received is None:
                waited = now - (started if not seqs else last)
                if waited > (STARTUP_TIMEOUT_S if not seqs else QUIET_END_S):
                    break
                continue
            last = now
            image = received.message
            latencies.append((received.received_ns - image.header.stamp_ns) / 1e6)
            seqs.append(image.header.seq)
            if len(seqs) == min(frames, 10):
                seen_nodes = {name for rig, name in live_nodes(session, keys, 1.0) if rig == keys.rig}
            if image.header.seq % max(1, round(fps)) == 0:
                print(f"frame {image.header.seq:5d}  {image.width}x{image.height} {image.encoding}  "
                      f"mean {float(image.data.mean()):6.1f}  latency {latencies[-1]:6.2f} ms", file=out, flush=True)
        supervisor.stop()
        return _summary(out, frames, seqs, latencies, seen_nodes, keys.echo(CAMERA), inbox.counter.dropped)
    finally:
        if supervisor is not None:
            supervisor.stop()
        session.close()


def _summary(out: TextIO, frames: int, seqs: list[int], latencies: list[float], nodes: set[str],
             key: str, dropped: int) -> int:
    in_order = all(a < b for a, b in zip(seqs, seqs[1:], strict=False))
    p50, p99 = (np.percentile(latencies, [50, 99]) if latencies else (float("nan"), float("nan")))
    rows = [
        ("frames published", str(frames)),
        ("frames received", f"{len(seqs)} on {key}"),
        ("lost / dropped", f"{frames - len(seqs)} / {dropped}"),
        ("in order", "yes" if in_order else "no"),
        ("latency p50 / p99", f"{p50:.2f} / {p99:.2f} ms (capture stamp -> here, 2 hops)"),
        ("nodes seen", ", ".join(sorted(nodes)) or "none"),
    ]
    print("\n".join(f"{name:>18}: {value}" for name, value in rows), file=out, flush=True)
    return 0 if len(seqs) == frames and in_order else 1
