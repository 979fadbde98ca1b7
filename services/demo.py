"""``artrack demo``: a bundled recording -> replay node -> echo node -> this client, over Zenoh.

Starts the ``replay`` node (playing ``recordings/markers.mcap``, restamped with the time each
frame goes out) and the ``echo`` node as separate processes, subscribes to the echo output
here, prints what flowed and a summary: frames, losses, end-to-end latency from the frame's
stamp to its arrival here (two process hops), and which nodes were seen on the bus.
"""

from __future__ import annotations

import signal
import sys
import threading
import time
from pathlib import Path
from typing import TextIO

import numpy as np

from protocol.sensors import Image
from services.launch import node_command
from services.observe import live_nodes
from services.recorder.info import summarise
from services.runtime.bus import BusConfig, open_session
from services.runtime.pubsub import Inbox, Role
from services.runtime.supervisor import ProcessSpec, Supervisor

CAMERA = "cam0"
STARTUP_TIMEOUT_S = 30.0
QUIET_END_S = 2.0


def echo_depth(fps: float) -> int:
    """Frames the demo's echo node may queue: about two seconds' worth."""
    return max(1, min(1000, round(2 * fps)))


DEFAULT_RECORDING = Path(__file__).resolve().parents[1] / "recordings" / "markers.mcap"


def recorded_frames(recording: Path) -> tuple[int, float, dict[str, str]]:
    """How many ``CAMERA`` images ``recording`` holds, their rate (Hz), and its namespace and rig."""
    if not recording.is_file():
        raise ValueError(f"{recording}: no such recording (the bundled ones are in recordings/)")
    info = summarise(recording)
    where = info.metadata.get("artrack.recording", {})
    for channel in info.channels:
        if channel.key.endswith(f"/{CAMERA}/image") and channel.messages > 1:
            rate = (channel.messages - 1) / ((channel.last_ns - channel.first_ns) / 1e9)
            return channel.messages, rate, {k: where[k] for k in ("namespace", "rig") if k in where}
    raise ValueError(f"{recording}: no {CAMERA} images in it")


def run_demo(bus: BusConfig, recording: Path = DEFAULT_RECORDING, out: TextIO = sys.stdout) -> int:
    """Run the demo; return 0 when every frame made it through, 1 otherwise."""
    frames, fps, where = recorded_frames(recording)
    bus = bus.model_copy(update=where)  # replay publishes on the recorded keys: work in their rig
    keys = bus.keys
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    session = open_session(bus)
    supervisor = None
    try:
        inbox = Inbox(session, keys.echo(CAMERA), Image, Role.FRAME, depth=1024)
        env = bus.to_env()
        supervisor = Supervisor([
            # Replaying only the images makes the replay wait for the echo node's subscription to them.
            ProcessSpec("replay", node_command("replay", "replay", {
                "path": str(recording), "keys": [f"{CAMERA}/image"], "restamp": True, "wait_s": STARTUP_TIMEOUT_S,
            }), env, restart=False),
            # The demo counts every frame, so the relay queues ~2 s of frames instead of keeping only
            # the newest: a busy machine's scheduling stalls must not show up as losses.
            ProcessSpec("echo", node_command("echo", "echo", {"camera": CAMERA, "depth": echo_depth(fps)}), env),
        ])
        supervisor.start()
        print(f"demo: nodes 'replay' ({recording.name}) and 'echo' on {keys.prefix}; {frames} frames at "
              f"{fps:.0f} fps. `artrack list` in another shell shows them.", file=out, flush=True)
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
        ("frames replayed", str(frames)),
        ("frames received", f"{len(seqs)} on {key}"),
        ("lost / dropped", f"{frames - len(seqs)} / {dropped}"),
        ("in order", "yes" if in_order else "no"),
        ("latency p50 / p99", f"{p50:.2f} / {p99:.2f} ms (replay stamp -> here, 2 hops)"),
        ("nodes seen", ", ".join(sorted(nodes)) or "none"),
    ]
    print("\n".join(f"{name:>18}: {value}" for name, value in rows), file=out, flush=True)
    return 0 if len(seqs) == frames and in_order else 1
