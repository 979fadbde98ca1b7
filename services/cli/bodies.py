"""``artrack bodies check`` and ``artrack bodies define``: bodies files looked over, and new bodies taken
from what the stereo tracker saw (its unlabelled points)."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

import numpy as np

log = logging.getLogger("artrack")

EXIT_WARNINGS = 1
CHECK_HELP = ("each body of a bodies file (spheres, shortest and longest distance) and the doubts the matcher has: "
              "exit 0 when none, 1 with warnings, 2 for a file that cannot be used")
DEFINE_HELP = ("a new body from a stereo recording's unlabelled points at one time, appended to a bodies file "
               "(body frame: origin at their centroid, principal axes)")
NS_PER_S = 1_000_000_000
SPAN_SLACK_S = 0.0005
"""How far ``--at`` may be outside a recording's span: half the millisecond the span is printed to."""


def spread(spheres: np.ndarray) -> str:
    """``N spheres, distances A to B mm``: the count and the shortest and longest sphere-to-sphere distance
    of (N, 3) sphere centres, metres."""
    from services.estimation.bodies.rigid import pairwise_distances

    distances = pairwise_distances(spheres)[np.triu_indices(len(spheres), 1)]
    return f"{len(spheres)} spheres, distances {distances.min() * 1e3:.1f} to {distances.max() * 1e3:.1f} mm"


def cmd_bodies_check(args: argparse.Namespace) -> int:
    from services.estimation.bodies.file import check_bodies, load_bodies

    bodies = load_bodies(args.file)
    for name, spheres in bodies.items():
        print(f"{name}: {spread(spheres)}")
    warnings = check_bodies(bodies)
    for warning in warnings:
        print(f"warning: {warning}")
    print(f"{len(bodies)} bodies, {len(warnings)} warning(s)")
    return EXIT_WARNINGS if warnings else 0


def unlabelled_points(recording: Path, at_s: float, key: str = "points") -> tuple[np.ndarray, float]:
    """The unlabelled points (body index -1) of the ``Points3D`` message on ``key`` whose stamp is nearest
    ``at_s`` seconds after the first one's: ``((N, 3) world, m; that message's time in seconds)``. ValueError
    for an ``at_s`` outside the span of the messages."""
    from protocol.mocap import Points3D
    from services.recorder.export import Export

    found: list[Points3D] = [m for _, _, m in Export(recording, key, "jsonl").messages() if isinstance(m, Points3D)]
    if not found:
        raise ValueError(f"{recording}: no Points3D messages on {key!r} (record a stereo tracker's run)")
    start = min(m.header.stamp_ns for m in found)
    span_s = (max(m.header.stamp_ns for m in found) - start) / NS_PER_S
    if not -SPAN_SLACK_S <= at_s <= span_s + SPAN_SLACK_S:
        raise ValueError(f"--at {at_s:g}: {recording} holds points from 0 to {span_s:.3f} s (after its first "
                         f"points message)")
    wanted = start + round(at_s * NS_PER_S)
    nearest = min(found, key=lambda m: abs(m.header.stamp_ns - wanted))
    return nearest.points[nearest.body == -1], (nearest.header.stamp_ns - start) / NS_PER_S


def cmd_bodies_define(args: argparse.Namespace) -> int:
    from services.estimation.bodies.definition import body_frame
    from services.estimation.bodies.file import NAME_PATTERN, check_bodies, load_bodies, parse_bodies, save_bodies

    if not NAME_PATTERN.fullmatch(args.name):
        raise ValueError(f"body name {args.name!r}: use letters, digits, '_', '.', '-'")
    bodies = load_bodies(args.bodies) if args.bodies.exists() else {}
    if args.name in bodies:
        raise ValueError(f"{args.bodies} already has a body {args.name!r}")
    points, at_s = unlabelled_points(args.recording, args.at)
    where = f"{args.recording} at {at_s:.3f} s"
    if len(points) < 3:
        raise ValueError(f"{where}: {len(points)} unlabelled point(s), a body needs at least 3")
    spheres, _ = body_frame(points)
    parse_bodies({"bodies": [{"name": args.name, "spheres": spheres.tolist()}]}, where)
    doubts = sorted((w for w in check_bodies({**bodies, args.name: spheres}) if repr(args.name) in w),
                    key=lambda w: not w.startswith(f"body {args.name!r}"))  # the new body's own first
    if doubts:
        raise ValueError(f"{where}: refused: {doubts[0]}")
    save_bodies(args.bodies, {**bodies, args.name: spheres})
    print(f"{args.name}: {spread(spheres)}, from {where}; appended to {args.bodies} ({len(bodies) + 1} bodies)")
    return 0


def add_bodies(sub: argparse._SubParsersAction) -> None:
    bodies = sub.add_parser("bodies", help="bodies files: `artrack bodies check`, `artrack bodies define`")
    bodies_sub = bodies.add_subparsers(dest="bodies_command", required=True, metavar="ACTION")
    p = bodies_sub.add_parser("check", help=CHECK_HELP, description=CHECK_HELP)
    p.add_argument("file", type=Path, metavar="FILE.yaml")
    p.set_defaults(func=cmd_bodies_check)
    p = bodies_sub.add_parser("define", help=DEFINE_HELP, description=DEFINE_HELP)
    p.add_argument("name", metavar="NAME", help="the new body's name (its pose key's last part)")
    p.add_argument("--from", dest="recording", required=True, type=Path, metavar="RECORDING.mcap",
                   help="a recording of `artrack run stereo` (its points key)")
    p.add_argument("--at", required=True, type=float, metavar="SECONDS",
                   help="when: seconds after the recording's first points message (the nearest one is taken)")
    p.add_argument("--bodies", type=Path, default=Path("bodies.yaml"), metavar="FILE.yaml",
                   help="the bodies file to append to, created when absent (default bodies.yaml); its bodies are "
                        "the ones the new body must not resemble")
    p.set_defaults(func=cmd_bodies_define)
