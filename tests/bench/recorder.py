"""Recorder and replay benchmark: ``bench_recorder()`` returns one JSON-ready dict per figure.

* ``record``: a camera-emulator process publishes ``CAMERAS`` cameras of 640x480 mono8 at
  ``FPS`` for ``SECONDS`` (an ``Image`` with the FRAME role's QoS and a ``CameraInfo`` with the
  RESULT role's per frame, as the capture node does; the pixels are a gradient plus sensor-like
  noise, so compression has real work). ``artrack record`` runs as its own process on a private
  router. Afterwards the file is read back: messages per key against those sent (``lost``),
  the recorder's own overflow count (``recorder_dropped``, from the file's metadata), sustained
  payload MiB/s and messages/s over the span of the recorded camera traffic, the file size
  (noisy frames barely compress), and the recorder process's CPU time, start-up included.
* ``replay``: the recording is replayed at rate 1 by ``replay_node.replay`` running in this
  process (a real node on the same router), into a second ``artrack record`` process.
  Timing error = |time each publication began - time it was due|, measured at the replayer
  (p50, p99, max); ``delivered`` counts what the second recorder got of what was replayed.
  At every frame tick the recorder logs a burst of messages closer together than the
  replayer can read and publish them, so the later messages of a burst are late by
  construction; ``_after_gap`` is the p99 over the messages recorded at
  least ``MIN_GAP_NS`` after the previous one: the pacing accuracy itself.

``python -m tests.bench.recorder cameras N FPS SECONDS`` is the emulator; it prints one JSON
line ``{"sent": {key: count}}``. The whole benchmark takes about 35 s.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from protocol import CameraInfo, Header, Image, decode
from services.bus.pubsub import Publisher, Role
from services.bus.session import BusConfig, open_session
from services.recorder.reading import Scan
from services.recorder.replay_node import Params, replay
from services.recorder.writing import RECORDER_METADATA
from services.runtime.memory import tune_malloc
from services.runtime.node import Node
from tests.bench.link import Bench, cpu_seconds

CAMERAS = 4
FPS = 30.0
SECONDS = 10.0
WIDTH, HEIGHT = 640, 480
VARIANTS = 8
MATCH_S = 20.0
MIN_GAP_NS = 2_000_000
LINGER_S = 0.5
"""Pause between the last frame and closing the session, so nothing is left in flight."""
MIB = 1 << 20
K = (500.0, 0.0, WIDTH / 2, 0.0, 500.0, HEIGHT / 2, 0.0, 0.0, 1.0)


def frames(camera: int) -> list[np.ndarray]:
    """``VARIANTS`` mono8 frames: a gradient that differs per camera, plus noise of sigma 4."""
    rng = np.random.default_rng(camera)
    base = (np.add.outer(np.arange(HEIGHT), np.arange(WIDTH) * (camera + 1)) % 256).astype(np.float32)
    return [np.clip(base + rng.normal(0, 4, base.shape), 0, 255).astype(np.uint8) for _ in range(VARIANTS)]


def emulate_cameras(cameras: int, fps: float, seconds: float) -> dict[str, int]:
    """Publish the cameras' frames and calibrations on the bus from the environment; counts per key."""
    bus = BusConfig.from_env()
    session = open_session(bus)
    try:
        names = [f"cam{i}" for i in range(cameras)]
        images = [Publisher(session, bus.keys.image(n), Image, Role.FRAME) for n in names]
        infos = [Publisher(session, bus.keys.camera_info(n), CameraInfo, Role.RESULT) for n in names]
        pixels = [frames(i) for i in range(cameras)]
        deadline = time.monotonic() + MATCH_S
        while not all(p.matched() for p in images + infos):
            if time.monotonic() > deadline:
                raise RuntimeError("the recorder did not subscribe")
            time.sleep(0.01)
        time.sleep(0.3)
        due = time.monotonic()
        for seq in range(int(fps * seconds)):
            for i, name in enumerate(names):
                header = Header(stamp_ns=time.time_ns(), frame_id=name, seq=seq)
                images[i].put(Image(header=header, encoding="mono8", data=pixels[i][seq % VARIANTS]))
                infos[i].put(CameraInfo(header=header, width=WIDTH, height=HEIGHT, k=K))
            due += 1.0 / fps
            time.sleep(max(0.0, due - time.monotonic()))
        time.sleep(LINGER_S)
        for publisher in images + infos:
            publisher.close()
        return {p.key: p.counter.messages for p in images + infos}
    finally:
        session.close()


def stop(child: subprocess.Popen) -> None:
    child.send_signal(signal.SIGINT)
    if child.wait(30) != 0:
        raise RuntimeError(f"{child.args} exited with {child.returncode}")


@dataclass
class Traffic:
    """The camera keys' messages in a recording: header sequence numbers per key, payload bytes,
    first and last log time, and the recorder's notes about itself."""

    seqs: dict[str, list[int]] = field(default_factory=dict)
    payload_bytes: int = 0
    first_ns: int = 0
    last_ns: int = 0
    notes: dict[str, str] = field(default_factory=dict)

    @property
    def messages(self) -> int:
        return sum(len(s) for s in self.seqs.values())

    def missing(self, sent: dict[str, int]) -> dict[str, list[int]]:
        """Sequence numbers sent but not recorded, per key (keys with none missing left out)."""
        gaps = {key: sorted(set(range(n)) - set(self.seqs.get(key, []))) for key, n in sent.items()}
        return {key: seqs for key, seqs in gaps.items() if seqs}


def camera_traffic(path: Path) -> Traffic:
    traffic = Traffic()
    scan = Scan(path)
    for recorded in scan.messages():
        topic = recorded.channel.topic
        if topic.endswith(("/image", "/camera_info")):
            traffic.seqs.setdefault(topic, []).append(decode(recorded.message.data).header.seq)
            traffic.payload_bytes += len(recorded.message.data)
            traffic.first_ns = traffic.first_ns or recorded.message.log_time
            traffic.last_ns = recorded.message.log_time
    traffic.notes = scan.metadata.get(RECORDER_METADATA, {})
    return traffic


def record_figure(bench: Bench, out: Path) -> dict[str, Any]:
    recorder = bench.start("record", str(out), "--name", "recorder")
    cameras = bench.start("cameras", str(CAMERAS), str(FPS), str(SECONDS), module="tests.bench.recorder")
    sent = json.loads(cameras.communicate(timeout=SECONDS + 60)[0])["sent"]
    time.sleep(1.0)
    cpu = cpu_seconds(recorder.pid)
    stop(recorder)
    traffic = camera_traffic(out)
    span = (traffic.last_ns - traffic.first_ns) / 1e9
    return {
        "bench": "recorder", "figure": "record", "cameras": CAMERAS, "resolution": f"{WIDTH}x{HEIGHT} mono8",
        "fps": FPS, "seconds": SECONDS, "sent": sum(sent.values()), "recorded": traffic.messages,
        "lost": sum(sent.values()) - traffic.messages, "missing": traffic.missing(sent),
        "recorder_dropped": int(traffic.notes.get("dropped", -1)),
        "msg_per_s": round((traffic.messages - 1) / span, 1),
        "payload_mib_per_s": round(traffic.payload_bytes / MIB / span, 2),
        "payload_mib": round(traffic.payload_bytes / MIB, 1), "file_mib": round(out.stat().st_size / MIB, 1),
        "recorder_cpu_s": round(cpu, 2), "target": "lost == 0", "met": sum(sent.values()) == traffic.messages,
    }


def replay_figure(bench: Bench, source: Path, out: Path) -> dict[str, Any]:
    recorder = bench.start("record", str(out), "--name", "recorder2")
    with Node("replay", "replay", bench.bus) as node:
        done = replay(node, Params(path=source, wait_s=MATCH_S))
    time.sleep(1.0)
    stop(recorder)
    error_ms = np.abs(np.array(done.lateness_ns)) / 1e6
    p50, p99, worst = np.percentile(error_ms, [50, 99, 100])
    log_times = np.array([r.message.log_time for r in Scan(source).messages() if "/node/" not in r.channel.topic])
    after_gap = error_ms[1:][np.diff(log_times) >= MIN_GAP_NS]
    replayed = camera_traffic(out)
    return {
        "bench": "recorder", "figure": "replay_timing", "rate": 1.0, "published": done.played,
        "delivered_camera_messages": replayed.messages,
        "timing_error_p50_ms": round(float(p50), 3), "timing_error_p99_ms": round(float(p99), 3),
        "timing_error_max_ms": round(float(worst), 3),
        "timing_error_p99_ms_after_gap": round(float(np.percentile(after_gap, 99)), 3),
        "messages_after_gap": int(after_gap.size),
    }


def bench_recorder() -> list[dict[str, Any]]:
    """Both figures (see the module docstring)."""
    tune_malloc()
    with tempfile.TemporaryDirectory(prefix="artrack-bench-") as folder, Bench(Path(folder)) as bench:
        first, second = Path(folder) / "cameras.mcap", Path(folder) / "replayed.mcap"
        return [record_figure(bench, first), replay_figure(bench, first, second)]


if __name__ == "__main__":
    if len(sys.argv) == 5 and sys.argv[1] == "cameras":
        tune_malloc()
        print(json.dumps({"sent": emulate_cameras(int(sys.argv[2]), float(sys.argv[3]), float(sys.argv[4]))}),
              flush=True)
    elif len(sys.argv) == 1:
        for line in bench_recorder():
            print(json.dumps(line), flush=True)
    else:
        sys.exit(f"usage: python -m tests.bench.recorder [cameras N FPS SECONDS], not {sys.argv[1:]}")
