"""``artrack scene export``: a synthetic scene written to files (images per camera, calibration, its fixtures,
ground truth as TUM), see ``services.launcher.scene_export``."""

from __future__ import annotations

import argparse
from pathlib import Path

from services.cli.run import scene_option_texts

EXPORT_HELP = ("write a synthetic scene's frames to files: a folder of images per camera (named by their time), "
               "rig, bodies, target and marker map files, ground truth as TUM per body")


def cmd_scene_export(args: argparse.Namespace) -> int:
    from services.launcher.scene_export import export_scene
    from services.synthetic import scene_options

    scheme, _, name = args.scene.partition(":")
    if scheme != "synthetic" or not name:
        raise ValueError(f"{args.scene!r}: give a scene as synthetic:SCENE (e.g. synthetic:ir_rig)")
    texts: dict[str, object] = {**scene_option_texts(args.scene_option)}
    options = scene_options(name, texts)
    done = export_scene(name, args.out, args.frames, options)
    print(f"wrote {done.folder}: {done.frames} frames of {len(done.cameras)} camera(s) "
          f"({', '.join(f'{camera}/' for camera in done.cameras)}), {done.images} images")
    fixtures = done.fixtures
    for path in (fixtures.rig, fixtures.bodies, fixtures.targets, fixtures.marker_map):
        if path is not None:
            print(f"wrote {path}")
    for path, rows in done.truth.items():
        print(f"wrote {path}: {rows} poses")
    for note in fixtures.notes:
        print(note)
    return 0


def add_scene(sub: argparse._SubParsersAction) -> None:
    scene = sub.add_parser("scene", help="synthetic scenes as files: `artrack scene export`")
    scene_sub = scene.add_subparsers(dest="scene_command", required=True, metavar="ACTION")
    p = scene_sub.add_parser("export", help=EXPORT_HELP, description=EXPORT_HELP)
    p.add_argument("scene", metavar="synthetic:SCENE", help="the scene (ir_rig, markers, planar_target, room, pattern)")
    p.add_argument("--frames", type=int, required=True, metavar="N", help="frames to write (1 or more)")
    p.add_argument("-o", "--out", type=Path, required=True, metavar="DIR", help="output folder (absent or empty)")
    p.add_argument("--scene-option", action="append", metavar="NAME=VALUE", help="a scene option, as for "
                   "`artrack run` (repeatable)")
    p.set_defaults(func=cmd_scene_export)
