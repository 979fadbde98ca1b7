"""How long ``artrack`` takes to refuse a command that cannot work: ``bench_refusals()`` -> one JSON-able dict
per case.

Each case is one command, run as the launcher runs artrack (``python -m services.cli``), that must end
with exit code 2 and one error line: sources that do not exist or cannot be read and map files or options
the SLAM node cannot use (refused before any process starts, as ``tests/integration/test_slam_sources.py``
and ``test_slam_map_files.py`` assert), and a command with no router to reach (``test_bus_errors.py``).
The ``start`` case (``artrack --version``, exit 0 and no line) is the floor: starting the interpreter
and the CLI.

The cases run round-robin ``RUNS`` times (a slow spell of the machine hits them alike); figures are the
wall time from starting the process to its exit, p50 and max over the runs, in seconds. The commands
see no router (``ARTRACK_ROUTER_AUTOSTART=0``, an endpoint nothing listens on), so a command that was
not refused could not start a job. A case that does not exit 2 with one line stops the benchmark.
``python -m tests.bench.refusals`` prints the lines.
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from tests.bench.link import ROOT, free_port

RUNS = 5
TIMEOUT_S = 60.0
REFUSED = 2


def cases(folder: Path, endpoint: str) -> dict[str, list[str]]:
    """``{case: artrack argv}``; ``folder`` holds the damaged files some of them name."""
    garbage_video, garbage_map = folder / "garbage.mkv", folder / "garbage.npz"
    garbage_video.write_bytes(b"not a video, " * 400)
    garbage_map.write_bytes(b"not a map, " * 100)
    slam = ["run", "slam", "--source", "synthetic:room", "--frames", "5"]
    return {
        "start": ["--version"],
        "missing_video": ["run", "slam", "--source", "video:/nope.mkv", "--depth", "5"],
        "missing_recording": ["run", "slam", "--source", "recording:/nope.mcap", "--depth", "5"],
        "garbage_video": ["run", "slam", "--source", f"video:{garbage_video}", "--depth", "5"],
        "garbage_map": [*slam, "--map", str(garbage_map)],
        "missing_map": [*slam, "--map", str(folder / "missing.npz")],
        "localisation_without_map": [*slam, "--localisation-only"],
        "save_map_in_no_folder": [*slam, "--save-map", "/no/such/folder/room.map.npz"],
        "no_router": ["list", "--timeout", "0.5", "--mode", "client", "--connect", endpoint],
    }


def timed(argv: list[str], env: dict[str, str]) -> tuple[float, int, list[str]]:
    """Seconds from start to exit of ``artrack argv``, its exit code and its non-blank stderr lines."""
    started = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "services.cli", *argv], cwd=ROOT, env=env, capture_output=True,
                          text=True, timeout=TIMEOUT_S, stdin=subprocess.DEVNULL)
    seconds = time.perf_counter() - started
    return seconds, done.returncode, [line for line in done.stderr.splitlines() if line.strip()]


def _shown(argv: list[str], folder: str, endpoint: str) -> str:
    """``argv`` as a command line, the damaged files' folder as ``DIR`` and the dead endpoint's port as ``PORT``."""
    return " ".join(["artrack", *argv]).replace(folder, "DIR").replace(endpoint, "tcp/127.0.0.1:PORT")


def bench_refusals() -> list[dict[str, Any]]:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    env = {**os.environ, "ARTRACK_ROUTER_AUTOSTART": "0", "ARTRACK_CONNECT": endpoint}
    with tempfile.TemporaryDirectory(prefix="artrack-refusals-") as folder:
        argvs = cases(Path(folder), endpoint)
        seconds: dict[str, list[float]] = {name: [] for name in argvs}
        for _ in range(RUNS):
            for name, argv in argvs.items():
                took, code, lines = timed(argv, env)
                expected = (0, 0) if name == "start" else (REFUSED, 1)
                if (code, len(lines)) != expected:
                    raise RuntimeError(f"{name}: `artrack {' '.join(argv)}` exited {code} with "
                                       f"{len(lines)} error lines, expected {expected}: {lines}")
                seconds[name].append(took)
        return [{"bench": "refusals", "case": name, "command": _shown(argvs[name], folder, endpoint),
                 "runs": RUNS, "p50_s": round(statistics.median(values), 3), "max_s": round(max(values), 3),
                 "runs_s": [round(v, 3) for v in values]} for name, values in seconds.items()]


if __name__ == "__main__":
    for line in bench_refusals():
        print(json.dumps(line), flush=True)
