"""A node for the integration tests that joins two cameras' images and republishes each pair.

    python syncnode.py NAME --by seq|stamp [--tolerance-ms MS] [--depth N] [--role result|frame] [--backlog N]
                       [--work-ms MS]

Runs as node NAME on the bus of the ``ARTRACK_*`` environment, joins ``cam0/image`` and
``cam1/image`` with ``Node.synced`` (role ``result``: every complete pair is handed out, in
order; ``frame``, or any role given ``--backlog``: only the newest ``--backlog``, 1 by default),
spends ``--work-ms`` on each pair as a slow node would, and publishes the two images of each pair
on ``<NAME>/cam0`` and ``<NAME>/cam1`` (role RESULT), so the i-th message of each forms the i-th
pair. What it could not join shows in its ``NodeStats.synced``.
"""

from __future__ import annotations

import argparse
import sys
import time

from protocol.sensors import Image
from services.bus.pubsub import Role
from services.bus.session import BusConfig
from services.runtime.logs import setup_logging
from services.runtime.node import Node, run_node

CAMERAS = ("cam0", "cam1")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("name")
    parser.add_argument("--by", choices=["seq", "stamp"], required=True)
    parser.add_argument("--tolerance-ms", type=float, default=0.0)
    parser.add_argument("--depth", type=int, default=8)
    parser.add_argument("--role", choices=["result", "frame"], default="result")
    parser.add_argument("--backlog", type=int)
    parser.add_argument("--work-ms", type=float, default=0.0)
    args = parser.parse_args(argv)
    setup_logging()

    def body(node: Node) -> None:
        pairs = node.synced({camera: node.keys.image(camera) for camera in CAMERAS}, Image, Role(args.role),
                            by=args.by, tolerance_s=args.tolerance_ms / 1e3, depth=args.depth, backlog=args.backlog)
        outs = {camera: node.publisher(f"{node.keys.prefix}/{args.name}/{camera}", Image) for camera in CAMERAS}
        for pair in pairs:
            time.sleep(args.work_ms / 1e3)
            for camera, image in pair.items():
                outs[camera].put(image)

    return run_node(args.name, "syncpairs", BusConfig.from_env(), body)


if __name__ == "__main__":
    sys.exit(main())
