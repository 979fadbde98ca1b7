"""The subscribing process of the benchmark, driven by the bench process over stdin/stdout.

``python -m tests.bench.sink ENDPOINT`` listens on ENDPOINT, answers ``{"ready": true}`` and
then obeys one JSON command per stdin line, answering each with one stdout line that
starts with ``REPLY`` (anything else on stdout, such as Zenoh's own logs, is not a reply):

* ``{"cmd": "start", "key": K, "reader": SPEC}``: subscribe to K. Every sample is read by
  ``traffic.reader(SPEC)`` (decoded, or viewed with ``np.frombuffer``), then its arrival time
  ``time.time_ns()`` is recorded next to the stamp the reader returned.
* ``{"cmd": "stop", "sent": N}``: wait until N samples have arrived, or none has for
  ``IDLE_S``; unsubscribe; answer how many arrived, the first and last arrival times (ns),
  the one-way latencies (µs) in arrival order, and how many samples the reader refused.
* ``{"cmd": "quit"}``: close the session and exit.

The callback runs on Zenoh's receiving thread (``indirect=False``): no queue between Zenoh and
the reader, so a reader slower than the publisher holds back the transport and, with
``CongestionControl.BLOCK``, the publisher, instead of piling samples up in memory.
"""

from __future__ import annotations

import json
import sys
import time
from typing import Any

import zenoh

from services.client.transport import session_config
from services.runtime.memory import tune_malloc
from tests.bench.traffic import reader

REPLY = "REPLY "
IDLE_S = 3.0


class Recording:
    """Samples arriving on one key: stamps and arrival times, in arrival order."""

    def __init__(self, session: zenoh.Session, key: str, spec: dict[str, Any]):
        read = reader(spec)
        self.stamps: list[int] = []
        self.arrivals: list[int] = []
        self.refused = 0

        def on_sample(sample: zenoh.Sample) -> None:
            try:
                stamp = read(sample)
            except Exception:  # a broken payload must show in the report, not kill Zenoh's thread
                self.refused += 1
                return
            self.arrivals.append(time.time_ns())
            self.stamps.append(stamp)

        self._subscriber = session.declare_subscriber(key, zenoh.handlers.Callback(on_sample, indirect=False))

    def finish(self, sent: int) -> dict[str, Any]:
        """Wait for ``sent`` samples (or ``IDLE_S`` of silence), unsubscribe, report."""
        seen, quiet_since = -1, time.monotonic()
        while len(self.arrivals) + self.refused < sent:
            if len(self.arrivals) != seen:
                seen, quiet_since = len(self.arrivals), time.monotonic()
            elif time.monotonic() - quiet_since > IDLE_S:
                break
            time.sleep(0.01)
        self._subscriber.undeclare()
        n = min(len(self.arrivals), len(self.stamps))
        arrivals = self.arrivals[:n]
        return {
            "received": n,
            "refused": self.refused,
            "first_ns": arrivals[0] if n else None,
            "last_ns": arrivals[-1] if n else None,
            "latencies_us": [(a - s) / 1e3 for a, s in zip(arrivals, self.stamps[:n], strict=True)],
        }


def reply(document: dict[str, Any]) -> None:
    sys.stdout.write(REPLY + json.dumps(document) + "\n")
    sys.stdout.flush()


def serve(session: zenoh.Session) -> None:
    """Obey commands from stdin until ``quit`` or end of input."""
    recording: Recording | None = None
    for line in sys.stdin:
        command = json.loads(line)
        if command["cmd"] == "start":
            recording = Recording(session, command["key"], command["reader"])
            reply({"started": command["key"]})
        elif command["cmd"] == "stop" and recording is not None:
            reply(recording.finish(command["sent"]))
            recording = None
        elif command["cmd"] == "quit":
            return
        else:
            reply({"error": f"unexpected command {command!r}"})


def main() -> None:
    tune_malloc()
    zenoh.init_log_from_env_or("error")
    session = zenoh.open(session_config("peer", listen=(sys.argv[1],)))
    try:
        reply({"ready": True})
        serve(session)
    finally:
        session.close()


if __name__ == "__main__":
    main()
