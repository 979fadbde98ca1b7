"""``artrack target add|list|show|remove|check``: image targets in a target library, and how trackable an
image is before it is printed."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import numpy as np

    from services.detection.keypoints.detector import KeypointParams
    from services.estimation.targets.check import Trackability
    from services.estimation.targets.library import TargetLibrary

log = logging.getLogger("artrack")

EXIT_WARNINGS = 1
EXIT_POOR = 2
CHECK_HELP = ("how trackable an image is as a target (keypoint count, spread, repeated texture): exit 0 when good, "
              "1 with warnings, 2 when poor or unreadable")


def library(args: argparse.Namespace) -> TargetLibrary:
    """The target library of ``--targets`` (default: the user's)."""
    from services.estimation.targets.library import TargetLibrary

    return TargetLibrary(args.targets)


def detector_of(feature: str | None) -> KeypointParams:
    """The detector settings of ``--feature`` (None: the default feature); ValueError for an unknown one."""
    from services.estimation.targets.features import DEFAULT_FEATURE, feature_params

    return feature_params(feature or DEFAULT_FEATURE)


def rating(report: Trackability) -> str:
    """``VERDICT: N keypoints, coverage C, spread S, repeated R``: a trackability report in one line."""
    return (f"{report.verdict}: {report.keypoints} keypoints, coverage {report.coverage:.0%}, spread "
            f"{report.entropy:.2f}, repeated {report.repeated:.0%}")


def print_check(image: np.ndarray, detector: KeypointParams) -> int:
    """Print the trackability of ``image`` with ``detector``'s keypoints; the exit status of its verdict."""
    from services.estimation.targets.check import check_image

    report = check_image(image, detector)
    print(rating(report))
    for warning in report.warnings:
        print(f"warning: {warning}")
    return {"good": 0, "fair": EXIT_WARNINGS, "poor": EXIT_POOR}[report.verdict]


def cmd_add(args: argparse.Namespace) -> int:
    from services.estimation.targets.check import check_image

    targets = library(args)
    detector = detector_of(args.feature)
    target = targets.add(args.image, args.width, args.target_name, detector)
    print(f"{target.name}: {target.size_px[0]}x{target.size_px[1]} px, {target.width_m:.3f} x {target.height_m:.3f} m, "
          f"{len(target.keypoints)} {target.feature} keypoints; added to {targets.folder}")
    report = check_image(target.image, detector)
    if report.verdict != "good":
        log.warning("%s rates %s (`artrack target check %s` says why)", args.image, rating(report), args.image)
    return 0


def cmd_list(args: argparse.Namespace) -> int:
    targets = library(args)
    found = targets.list()
    if not found:
        print(f"no targets in {targets.folder}")
    for info in found:
        print(f"{info.name}: {info.width_m:.3f} x {info.height_m:.3f} m, {info.image_size[0]}x{info.image_size[1]} px, "
              f"{info.keypoints} {info.feature} keypoints")
    return 0


def cmd_show(args: argparse.Namespace) -> int:
    from services.estimation.targets.features import CAP_FRAME_PX, has_scale_space

    targets = library(args)
    info = targets.info(args.target)
    print(f"target: {info.name} ({info.path})")
    print(f"source: {info.source}")
    print(f"size: {info.image_size[0]}x{info.image_size[1]} px, {info.width_m:.3f} x {info.height_m:.3f} m")
    per = "per {}x{} pixels".format(*CAP_FRAME_PX) if has_scale_space(info.detector) else "per level"
    print(f"detector: {info.detector.method}, at most {info.detector.max_count} keypoints {per}")
    print(f"descriptors: {info.descriptor}")
    levels = ", ".join(f"{count} at 1/{2**level}" for level, count in enumerate(info.per_level))
    print(f"keypoints: {info.keypoints} ({levels})")
    print("check: ", end="")
    print_check(targets.load(args.target).image, info.detector)
    return 0


def cmd_remove(args: argparse.Namespace) -> int:
    targets = library(args)
    targets.remove(args.target)
    print(f"{args.target}: removed from {targets.folder}")
    return 0


def cmd_check(args: argparse.Namespace) -> int:
    from services.estimation.targets.library import read_image

    return print_check(read_image(args.image), detector_of(args.feature))


def add_targets_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--targets", type=Path, metavar="DIR",
                        help="the target library (default $XDG_DATA_HOME/artrack/targets, else "
                             "~/.local/share/artrack/targets)")


FEATURE_HELP = "the keypoints: orb (default) or sift"


def add_target(sub: argparse._SubParsersAction) -> None:
    target = sub.add_parser("target", help="image targets: `artrack target add|list|show|remove|check`")
    actions = target.add_subparsers(dest="target_command", required=True, metavar="ACTION")
    p = actions.add_parser("add", help="build a target from an image and add it to the library")
    p.add_argument("image", type=Path, metavar="IMAGE")
    p.add_argument("--width", required=True, type=float, metavar="M", help="the printed image's width, metres")
    p.add_argument("--name", dest="target_name", metavar="NAME", help="the target's name (default: the file's stem)")
    p.add_argument("--feature", metavar="orb|sift", help=FEATURE_HELP)
    add_targets_option(p)
    p.set_defaults(func=cmd_add)
    p = actions.add_parser("list", help="the library's targets")
    add_targets_option(p)
    p.set_defaults(func=cmd_list)
    p = actions.add_parser("show", help="one target: size, keypoints per level, descriptors and its check")
    p.add_argument("target", metavar="NAME")
    add_targets_option(p)
    p.set_defaults(func=cmd_show)
    p = actions.add_parser("remove", help="delete a target and its image from the library")
    p.add_argument("target", metavar="NAME")
    add_targets_option(p)
    p.set_defaults(func=cmd_remove)
    p = actions.add_parser("check", help=CHECK_HELP, description=CHECK_HELP)
    p.add_argument("image", type=Path, metavar="IMAGE")
    p.add_argument("--feature", metavar="orb|sift", help=FEATURE_HELP)
    p.set_defaults(func=cmd_check)
