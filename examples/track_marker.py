"""Follow tracked markers from your own app: print each pose and how old it is on arrival.

Start a marker pipeline first (for instance ``artrack run marker --source synthetic:markers
--loop --marker-length 0.05``), then ``python examples/track_marker.py cam0/marker/3`` with the
checkout's ``.venv`` active (or ``.venv/bin/python examples/track_marker.py ...``). With no target
it follows every pose of the rig. The bus options are the nodes' own environment
variables (``ARTRACK_CONNECT``, ``ARTRACK_MODE``, ``ARTRACK_RIG``, ...).
"""

from __future__ import annotations

import argparse

from services.client import connect


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("target", nargs="?", default="**", help="a target, e.g. cam0/marker/3 (default: all)")
    parser.add_argument("--count", type=int, default=0, help="stop after this many poses (default: never)")
    parser.add_argument("--idle-timeout", type=float, metavar="S", help="stop after S seconds without a pose")
    args = parser.parse_args(argv)
    with connect(app="track_marker") as ar:
        try:
            for n, update in enumerate(ar.poses(args.target, idle_timeout_s=args.idle_timeout), start=1):
                x, y, z = update.pose.transform.translation
                print(f"{update.target} frame {update.pose.header.seq}: {update.pose.state.value} "
                      f"t = ({x:+.3f}, {y:+.3f}, {z:+.3f}) m, latency {update.latency_ms:.1f} ms", flush=True)
                if n == args.count:
                    break
        except KeyboardInterrupt:  # Ctrl-C is how a user stops following
            pass
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
