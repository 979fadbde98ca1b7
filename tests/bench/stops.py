"""How long a node and ``artrack up`` take to stop on SIGTERM: ``bench_stops()`` -> one JSON-able dict per case.

On a private router (``tests.bench.live.LiveBus``): an ``echo`` node and a ``capture`` node (one 64x64
synthetic camera at 20 fps), each its own process, and ``artrack up`` of a pipeline of the two (the
launcher and its two children). Each is started, given ``RUNNING_S`` once every node of it is live, then
sent SIGTERM; the figure is the wall time from the signal to the process's exit (for the launcher: its
nodes stopped too), p50 and max over ``RUNS`` rounds, in seconds, with the exit code of each run (0 is
a clean stop). A process still running ``STOP_S`` after the signal stops the benchmark.
``tests/integration/test_cli.py`` and ``test_launcher.py`` check that they stop, and leave the bus,
without timing it. ``python -m tests.bench.stops`` prints the lines.
"""

from __future__ import annotations

import json
import signal
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from services.launcher.observe import wait_for_nodes
from services.launcher.pipeline import node_command
from tests.bench.live import START_S, LiveBus

RUNS = 5
RUNNING_S = 0.5
STOP_S = 30.0
CAMERA: dict[str, Any] = {"cameras": ["cam0"], "fps": 20, "scene": {"width": 64, "height": 64}}


def pipeline(live: LiveBus, suffix: str) -> str:
    """The ``artrack up`` file: nodes ``cam{suffix}`` (capture of ``CAMERA``) and ``echo{suffix}`` on ``live``'s bus."""
    return f"""
[bus]
rig = "{live.bus.rig}"
connect = ["{live.endpoint}"]
autostart_router = false

[nodes.cam{suffix}]
kind = "capture"
cameras = ["cam0"]
fps = {CAMERA["fps"]}
scene = {{ width = {CAMERA["scene"]["width"]}, height = {CAMERA["scene"]["height"]} }}

[nodes.echo{suffix}]
kind = "echo"
camera = "cam0"
"""


def stop_seconds(live: LiveBus, argv: list[str], names: set[str]) -> tuple[float, int]:
    """Start ``argv`` on ``live``'s bus, wait until ``names`` are live and ``RUNNING_S`` more, SIGTERM it:
    the seconds until it has exited, and its exit code."""
    process = live.start(argv)
    if wait_for_nodes(live.session, live.bus.keys, names, START_S) != names:
        raise RuntimeError(f"`{' '.join(argv)}`: {sorted(names)} did not come up")
    time.sleep(RUNNING_S)
    signalled = time.perf_counter()
    process.send_signal(signal.SIGTERM)
    code = process.wait(STOP_S)
    return time.perf_counter() - signalled, code


def bench_stops() -> list[dict[str, Any]]:
    runs: dict[str, list[tuple[float, int]]] = {"echo_node": [], "capture_node": [], "launcher": []}
    with tempfile.TemporaryDirectory(prefix="artrack-stops-") as folder, LiveBus("stops") as live:
        for round_ in range(RUNS):
            echo, capture, path = f"echo{round_}", f"cam{round_}", Path(folder) / f"pipeline{round_}.toml"
            runs["echo_node"].append(stop_seconds(live, [*node_command("echo", echo, {"camera": "cam0"})], {echo}))
            runs["capture_node"].append(stop_seconds(live, [*node_command("capture", capture, CAMERA)], {capture}))
            path.write_text(pipeline(live, f"_up{round_}"))
            runs["launcher"].append(stop_seconds(live, [sys.executable, "-m", "services.cli", "up", str(path)],
                                                 {f"cam_up{round_}", f"echo_up{round_}"}))
    lines = []
    for name, measured in runs.items():
        seconds = [s for s, _ in measured]
        lines.append({"bench": "stops", "case": name, "signal": "SIGTERM", "runs": RUNS,
                      "p50_s": round(statistics.median(seconds), 3), "max_s": round(max(seconds), 3),
                      "runs_s": [round(s, 3) for s in seconds], "exit_codes": [code for _, code in measured]})
    return lines


if __name__ == "__main__":
    for line in bench_stops():
        print(json.dumps(line), flush=True)
