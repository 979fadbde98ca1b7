"""The subscribing process of the benchmark, driven by the bench process over stdin/stdout.

``python -m tests.bench.sink ENDPOINT`` listens on ENDPOINT as a plain Zenoh peer;
``python -m tests.bench.sink --app MODE ENDPOINT NAMESPACE RIG`` joins as a client app instead
(``services.client.connect`` in MODE, peer or client, to ENDPOINT) and receives poses the way
apps do, through ``Client.on_pose`` (the library decodes them; only the typed reader applies).
Either way it answers ``{"ready": true}`` and then obeys one JSON command per stdin line,
answering each with one stdout line that starts with ``REPLY`` (anything else on stdout,
such as Zenoh's own logs, is not a reply):

* ``{"cmd": "start", "key": K, "reader": SPEC}``: subscribe to K. Every sample is read by
  ``traffic.reader(SPEC)`` (decoded, or viewed with ``np.frombuffer``), or decoded by the
  client library, then its arrival time ``time.time_ns()`` is recorded next to its send stamp.
* ``{"cmd": "stop", "sent": N}``: wait until N samples have arrived, or none has for
  ``IDLE_S``; unsubscribe; answer how many arrived, the first and last arrival times (ns),
  the one-way latencies (µs) in arrival order, and how many samples the reader refused.
* ``{"cmd": "quit"}``: close the session and exit.

The plain peer's callback runs on Zenoh's receiving thread (``indirect=False``): no queue
between Zenoh and the reader, so a reader slower than the publisher holds back the transport
and, with ``CongestionControl.BLOCK``, the publisher, instead of piling samples up in memory.
The app's callback runs where the client library runs it.
"""

from __future__ import annotations

import json
import sys
import time
from collections.abc import Callable
from typing import Any

import zenoh

from services.bus.transport import session_config
from services.client import Client, connect
from services.runtime.memory import tune_malloc
from tests.bench.traffic import reader, typed_reader_spec

REPLY = "REPLY "
IDLE_S = 3.0


Subscribe = Callable[[Callable[[Any], None]], Callable[[], None]]
"""Starts a subscription that hands every message to the callback; returns what stops it."""


class Recording:
    """Messages arriving through one subscription: send stamps and arrival times, in arrival order.

    ``read(message)`` does the reading work and returns the message's send stamp.
    """

    def __init__(self, subscribe: Subscribe, read: Callable[[Any], int]):
        self.stamps: list[int] = []
        self.arrivals: list[int] = []
        self.refused = 0

        def on_message(message: Any) -> None:
            try:
                stamp = read(message)
            except Exception:  # a broken payload must show in the report, not kill Zenoh's thread
                self.refused += 1
                return
            self.arrivals.append(time.time_ns())
            self.stamps.append(stamp)

        self._stop = subscribe(on_message)

    def finish(self, sent: int) -> dict[str, Any]:
        """Wait for ``sent`` messages (or ``IDLE_S`` of silence), unsubscribe, report."""
        seen, quiet_since = -1, time.monotonic()
        while len(self.arrivals) + self.refused < sent:
            if len(self.arrivals) != seen:
                seen, quiet_since = len(self.arrivals), time.monotonic()
            elif time.monotonic() - quiet_since > IDLE_S:
                break
            time.sleep(0.01)
        self._stop()
        n = min(len(self.arrivals), len(self.stamps))
        arrivals = self.arrivals[:n]
        return {
            "received": n,
            "refused": self.refused,
            "first_ns": arrivals[0] if n else None,
            "last_ns": arrivals[-1] if n else None,
            "latencies_us": [(a - s) / 1e3 for a, s in zip(arrivals, self.stamps[:n], strict=True)],
        }


def peer_recording(session: zenoh.Session, key: str, spec: dict[str, Any]) -> Recording:
    """Samples on ``key``, read by ``traffic.reader(spec)`` on Zenoh's receiving thread."""
    def subscribe(on_sample: Callable[[zenoh.Sample], None]) -> Callable[[], None]:
        return session.declare_subscriber(key, zenoh.handlers.Callback(on_sample, indirect=False)).undeclare

    return Recording(subscribe, reader(spec))


def app_recording(client: Client, key: str, spec: dict[str, Any]) -> Recording:
    """Poses on the pose key ``key``, received and decoded by the client library."""
    if spec != typed_reader_spec():
        raise ValueError(f"a client app reads poses only, typed; not {spec}")
    target = client.keys.target(key)
    return Recording(lambda on_pose: client.on_pose(target, on_pose).close,
                     lambda update: update.pose.header.stamp_ns)


def reply(document: dict[str, Any]) -> None:
    sys.stdout.write(REPLY + json.dumps(document) + "\n")
    sys.stdout.flush()


def serve(open_recording: Callable[[str, dict[str, Any]], Recording]) -> None:
    """Obey commands from stdin until ``quit`` or end of input."""
    recording: Recording | None = None
    for line in sys.stdin:
        command = json.loads(line)
        if command["cmd"] == "start":
            try:
                recording = open_recording(command["key"], command["reader"])
            except ValueError as exc:
                reply({"error": str(exc)})
                continue
            reply({"started": command["key"]})
        elif command["cmd"] == "stop" and recording is not None:
            reply(recording.finish(command["sent"]))
            recording = None
        elif command["cmd"] == "quit":
            return
        else:
            reply({"error": f"unexpected command {command!r}"})


def main(argv: list[str]) -> None:
    tune_malloc()
    zenoh.init_log_from_env_or("error")
    if argv[:1] == ["--app"]:
        mode, endpoint, namespace, rig = argv[1:]
        with connect(mode=mode, connect=endpoint, namespace=namespace, rig=rig, app="bench_sink") as client:
            reply({"ready": True})
            serve(lambda key, spec: app_recording(client, key, spec))
        return
    session = zenoh.open(session_config("peer", listen=(argv[0],)))
    try:
        reply({"ready": True})
        serve(lambda key, spec: peer_recording(session, key, spec))
    finally:
        session.close()


if __name__ == "__main__":
    main(sys.argv[1:])
