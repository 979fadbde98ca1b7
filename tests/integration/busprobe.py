"""A tiny publisher process for the integration tests.

    python busprobe.py KIND COUNT [--key KEY] [--role result|frame] [--rate HZ]
                                  [--peer ZID] [--width W --height H]
                                  [--skip I,J,...] [--offset-ms MS] [--offset-at I=MS ...]

Opens a session from the ``ARTRACK_*`` environment (the test's router), waits until a
subscriber matches ``KEY`` (and, with ``--peer``, until the session of that Zenoh id is a
direct peer, so no message can take the longer way through the router), publishes
``make_message(KIND, i)`` for i in 0..COUNT-1 with the given role (leaving out the indices
of ``--skip``; stamps moved by ``--offset-ms``, or for index I by the MS of ``--offset-at I=MS``
instead: a second camera's stream with missing and skewed frames), prints one JSON line
``{"published": COUNT}``, then stays until no subscriber matches any more (the test closes its
subscriber once it has what it wants) and closes the session. The tests rebuild the same
messages with ``make_message`` to compare what arrived. Exit code 3: nothing subscribed
within the deadline.

Why stay: Zenoh carries large payloads between local processes in the sender's shared
memory, and a sender that exits right after ``put`` takes with it messages that the receiver
has not read yet (seen here as lost RESULT frames under CPU load). Publishers that exit
after their last message must give subscribers time to read it.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time

import numpy as np

from protocol.message import Header, Message
from protocol.poses import Pose, PoseQuality
from protocol.sensors import Image
from protocol.spatial import Transform
from protocol.tracking_state import TrackingState
from services.bus.pubsub import Publisher, Role
from services.bus.session import BusConfig, open_session

BASE_STAMP_NS = 1_700_000_000_000_000_000
MATCH_TIMEOUT_S = 20.0
LINGER_MAX_S = 60.0
KINDS = {"pose": Pose, "image": Image}


def make_message(kind: str, index: int, width: int = 320, height: int = 240) -> Message:
    """The ``index``-th message of ``kind``: deterministic, different for every index.

    ``pose``: a Pose with every field set (covariance on even indices); ``image``: a random
    bgr8 frame on even indices and a random mono16 one on odd indices, ``(height, width)``.
    """
    header = Header(stamp_ns=BASE_STAMP_NS + index * 33_333_333, frame_id="cam0", seq=index)
    if kind == "pose":
        angle = 0.01 * index
        return Pose(
            header=header, child_frame_id=f"marker/{index % 5}",
            transform=Transform(translation=(0.01 * index, -0.5 + 1e-3 * index, 1.0 + 1e-4 * index),
                                rotation=(0.0, 0.0, math.sin(angle / 2), math.cos(angle / 2))),
            state=list(TrackingState)[index % len(TrackingState)],
            quality=PoseQuality(reprojection_rms_px=0.1 + 1e-3 * index, inliers=4 + index % 7,
                                ambiguous=index % 2 == 1),
            covariance=tuple(1e-6 * (index + k) for k in range(36)) if index % 2 == 0 else None,
        )
    if kind == "image":
        rng = np.random.default_rng(index)
        if index % 2 == 0:
            return Image(header=header, encoding="bgr8",
                         data=rng.integers(0, 256, (height, width, 3), dtype=np.uint8))
        return Image(header=header, encoding="mono16", data=rng.integers(0, 65536, (height, width), dtype=np.uint16))
    raise ValueError(f"unknown kind {kind!r}")


def shifted(message: Message, offset_ms: float) -> Message:
    """``message`` with its header stamp moved by ``offset_ms``."""
    if not offset_ms:
        return message
    header = message.header.model_copy(update={"stamp_ns": message.header.stamp_ns + round(offset_ms * 1e6)})
    return message.model_copy(update={"header": header})


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("kind", choices=sorted(KINDS))
    parser.add_argument("count", type=int)
    parser.add_argument("--key", default="probe/out", help="relative to ar/<rig>/ unless it starts with the namespace")
    parser.add_argument("--role", choices=[r.value for r in Role], default="result")
    parser.add_argument("--rate", type=float, default=0.0, help="messages per second; 0 = as fast as possible")
    parser.add_argument("--peer", help="Zenoh id of the subscriber's session; wait for a direct link to it")
    parser.add_argument("--width", type=int, default=320)
    parser.add_argument("--height", type=int, default=240)
    parser.add_argument("--skip", default="", help="comma-separated indices not to publish")
    parser.add_argument("--offset-ms", type=float, default=0.0, help="added to every stamp")
    parser.add_argument("--offset-at", action="append", default=[], metavar="I=MS",
                        help="added to the stamp of index I instead of --offset-ms (repeatable)")
    args = parser.parse_args(argv)

    bus = BusConfig.from_env()
    skip = {int(i) for i in args.skip.split(",") if i}
    offsets_ms = {int(i): float(ms) for i, ms in (spec.split("=") for spec in args.offset_at)}
    messages = [shifted(make_message(args.kind, i, args.width, args.height), offsets_ms.get(i, args.offset_ms))
                for i in range(args.count) if i not in skip]
    session = open_session(bus)
    try:
        publisher = Publisher(session, bus.keys.resolve(args.key), KINDS[args.kind], Role(args.role))
        deadline = time.monotonic() + MATCH_TIMEOUT_S
        while not (publisher.matched() and (args.peer is None or args.peer in
                                              {str(z) for z in session.info.peers_zid()})):
            if time.monotonic() > deadline:
                print(json.dumps({"error": "no subscriber matched", "key": publisher.key}), flush=True)
                return 3
            time.sleep(0.01)
        started = next_at = time.monotonic()
        for message in messages:
            publisher.put(message)
            if args.rate > 0:
                next_at += 1.0 / args.rate
                time.sleep(max(0.0, next_at - time.monotonic()))
        print(json.dumps({"published": len(messages), "key": publisher.key,
                          "seconds": round(time.monotonic() - started, 3)}), flush=True)
        deadline = time.monotonic() + LINGER_MAX_S
        while publisher.matched() and time.monotonic() < deadline:
            time.sleep(0.02)
        publisher.close()
        return 0
    finally:
        session.close()


if __name__ == "__main__":
    sys.exit(main())
