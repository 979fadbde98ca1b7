"""Pose transport through a router against peer to peer, on loopback, side by side in one run.

The bench process publishes ``protocol.Pose`` messages (``traffic.PoseSender``: built, encoded
by the codec, put with the RESULT role's QoS, priority DATA_HIGH, congestion BLOCK)
on pose keys of the rig; a client app process (``tests.bench.sink --app``) receives them the
way apps do, through ``services.client`` (``Client.on_pose``, decoded by the library):

* ``peer``: the app connects as a peer straight to the publishing session (one hop);
* ``router``: both are client-mode sessions of a real ``artrack router`` process on a free
  loopback port, so every pose takes two hops (publisher -> router -> app).

Each run measures latency p50/p99 over ``LATENCY_N`` poses paced at ``RATE_HZ``, then zero-loss
throughput by flooding (``tests.bench.runs``). ``ROUNDS`` rounds, the variants' order
alternating; a variant's figures are medians over its runs, the router/peer ratios medians
over the rounds' pairs. ``python -m tests.bench.routing`` prints the lines (about 30 s).
"""

from __future__ import annotations

import json
import tempfile
from pathlib import Path
from typing import Any

from protocol import encode
from protocol.keys import Keys
from services.bus.pubsub import Role
from tests.bench.figures import alternating, paired_median, variant_line
from tests.bench.link import RIG, Bench, Sink, direct_app, routed_app
from tests.bench.runs import Run, measure
from tests.bench.traffic import PoseSender, pose_message, typed_reader_spec

ROUNDS = 3
RATE_HZ = 1000.0
LATENCY_N = 2000
BENCH = "pose_routing"


def ratio_line(router: list[Run], peer: list[Run]) -> dict[str, Any]:
    """Router/peer ratios of throughput and of latency p50 and p99, medians over paired runs."""
    def ratio(field: str) -> float:
        return round(paired_median([getattr(r, field) for r in router], [getattr(p, field) for p in peer]), 3)

    return {"bench": BENCH, "figure": "router_vs_peer", "msg_per_s_ratio": ratio("msg_per_s"),
            "latency_p50_ratio": ratio("latency_p50_us"), "latency_p99_ratio": ratio("latency_p99_us")}


def bench_routing() -> list[dict[str, Any]]:
    """Both variants' figures and their ratios (see the module docstring)."""
    keys = Keys(rig=RIG)
    with (tempfile.TemporaryDirectory(prefix="artrack-bench-routing-") as folder, Bench(Path(folder)) as bench,
          Sink(direct_app(keys)) as peer, Sink(routed_app(bench.endpoint, keys)) as routed):
        sinks = {"peer": peer, "router": routed}
        runs: dict[str, list[Run]] = {name: [] for name in sinks}
        for round_, name in alternating(list(sinks), ROUNDS):
            runs[name].append(measure(sinks[name], keys.pose(f"routing/{name}/{round_}"), typed_reader_spec(),
                                      PoseSender, Role.RESULT, Role.RESULT, rate_hz=RATE_HZ, latency_n=LATENCY_N))
    size = len(encode(pose_message(0)))
    variants = [{**variant_line(BENCH, name, size, runs[name]), "rate_hz": RATE_HZ,
                 "hops": 2 if name == "router" else 1} for name in runs]
    return [*variants, ratio_line(runs["router"], runs["peer"])]


if __name__ == "__main__":
    for line in bench_routing():
        print(json.dumps(line), flush=True)
