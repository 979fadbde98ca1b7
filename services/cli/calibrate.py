"""``artrack calibrate``: camera intrinsics from photos of a board, a stereo pair (--stereo), or a rig's
extrinsics from a recorded wand (--wand), set on the floor by an L-frame (--floor)."""

from __future__ import annotations

import argparse
import contextlib
from pathlib import Path
from typing import TYPE_CHECKING

from services.cli.outputs import add_force_option
from services.runtime.outputs import check_output

if TYPE_CHECKING:
    import numpy as np

    from services.calibration.intrinsics import Pattern
    from services.geometry.camera import CameraModel


IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm", ".webp")


def _image_files(where: str, pattern: str) -> list[Path]:
    """Image files of folder ``where`` matching ``pattern``, or those a glob ``where`` matches; sorted by path."""
    import glob

    folder = Path(where)
    candidates = folder.glob(pattern) if folder.is_dir() else (Path(p) for p in glob.glob(where))
    files = sorted(p for p in candidates if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)
    if not files:
        raise ValueError(f"no images ({', '.join(IMAGE_SUFFIXES)}) match {where}"
                         + (f" with --glob {pattern!r}" if folder.is_dir() else ""))
    return files


def _calibration_pattern(args: argparse.Namespace) -> Pattern:
    """The target ``artrack calibrate``'s --pattern, --size, --square, --marker and --dictionary describe."""
    from services.calibration.intrinsics import Charuco, Chessboard

    columns, _, rows = args.size.lower().partition("x")
    if not (columns.isdigit() and rows.isdigit()):
        raise ValueError(f"--size {args.size!r}: give COLSxROWS, e.g. 9x6")
    if args.pattern == "chessboard":
        return Chessboard(int(columns), int(rows), args.square)
    if args.marker is None or args.dictionary is None:
        raise ValueError("--pattern charuco needs --marker and --dictionary")
    return Charuco(int(columns), int(rows), args.square, args.marker, args.dictionary)


def cmd_calibrate(args: argparse.Namespace) -> int:
    import cv2

    from services.calibration.camera_info import write_camera_info
    from services.calibration.intrinsics import calibrate_images

    check_output(args.out, args.force)  # before the work: a calibration can take minutes
    if args.wand is not None:
        return cmd_calibrate_wand(args)
    missing = [flag for flag, value in (("DIR_OR_GLOB", args.images or None), ("--pattern", args.pattern),
                                        ("--size", args.size), ("--square", args.square)) if value is None]
    if missing:
        raise ValueError(f"calibrate needs {', '.join(missing)} (intrinsics from photos), or --wand (extrinsics)")
    if args.stereo:
        return _calibrate_stereo(args)
    if len(args.images) != 1:
        raise ValueError(f"one camera takes one DIR_OR_GLOB, got {len(args.images)}; "
                         "for a stereo pair add --stereo (LEFT RIGHT)")
    for option in ("names", "rig_frame", "refine_intrinsics"):
        if getattr(args, option) not in (None, False):
            raise ValueError(f"--{option.replace('_', '-')} is for --stereo")
    pattern = _calibration_pattern(args)
    files = _image_files(args.images[0], args.glob)
    images = ((path.name, cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)) for path in files)
    result = calibrate_images(images, pattern, args.camera)
    print(result.report())
    try:
        write_camera_info(args.out, result.camera)
    except OSError as exc:
        raise ValueError(f"cannot write {args.out}: {exc.strerror}") from exc
    print(f"wrote {args.out}")
    return 0


def cmd_calibrate_wand(args: argparse.Namespace) -> int:
    """Extrinsics of a recording's cameras from a wand waved before them, written as a rig file."""
    from dataclasses import replace

    import numpy as np

    from services.calibration.rig import Rig, write_rig
    from services.calibration.wand import Wand, calibrate_wand, reframe
    from services.convert import camera_model
    from services.recorder.camera_frames import camera_frames

    if args.wand_length is None or args.wand_middle is None:
        raise ValueError("--wand needs --wand-length (between the end spheres) and --wand-middle (the middle "
                         "sphere's distance from an end), metres")
    wand = Wand(np.array([0.0, args.wand_middle, args.wand_length]))
    recorded = camera_frames(args.wand, _ir_blobs)
    if len(recorded.cameras) < 2:
        raise ValueError(f"{args.wand}: wand calibration needs images of 2 or more cameras, found "
                         f"{recorded.cameras or 'none'}")
    given = _intrinsics(args.intrinsics or [])
    cameras = []
    for name in [c.name for c in given if c.name in recorded.cameras] or recorded.cameras:
        known = [c for c in given if c.name == name]
        if known:
            cameras.append(known[0])
        elif name in recorded.infos:
            cameras.append(camera_model(recorded.infos[name], name))
        else:
            raise ValueError(f"no intrinsics for camera {name!r}: the recording has no camera_info for it and "
                             "--intrinsics does not name it")
    names = [c.name for c in cameras]
    frames = [[frame.get(name, np.zeros((0, 2))) for name in names] for frame in recorded.frames.values()]
    result = calibrate_wand(cameras, frames, wand)
    print(result.report(names))
    placed = [replace(c, T_rig_camera=T) for c, T in zip(cameras, result.T_rig_camera, strict=True)]
    if args.floor is not None:
        T_rig_floor = _floor_frame(args.floor, placed)
        placed = [replace(c, T_rig_camera=T) for c, T in zip(cameras, reframe(result.T_rig_camera, T_rig_floor),
                                                              strict=True)]
    rig = Rig(args.out.stem, tuple(placed))
    try:
        write_rig(args.out, rig)
    except OSError as exc:
        raise ValueError(f"cannot write {args.out}: {exc.strerror}") from exc
    print(f"wrote {args.out}")
    return 0


def _ir_blobs(image: np.ndarray) -> np.ndarray:
    """(N, 2) centroids, px, of the clean blobs the IR detector finds in a mono (or BGR) image."""
    import cv2

    from services.detection.blobs.bright import detect_ir_blobs

    mono = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image
    return detect_ir_blobs(mono).clean().centroids


def _floor_frame(path: Path, cameras: list[CameraModel]) -> np.ndarray:
    """(4, 4) ``T_rig_floor`` of the L-frame recorded in ``path``: its spheres triangulated with the
    calibrated ``cameras`` in every frame that shows exactly three, ordered, then the median."""
    import numpy as np

    from services.calibration.camera_info import CalibrationError
    from services.calibration.wand import floor_frame, order_lframe
    from services.estimation.bodies.correspondence import triangulate_blobs
    from services.recorder.camera_frames import camera_frames

    recorded = camera_frames(path, _ir_blobs)
    found = []
    for frame in recorded.frames.values():
        points = triangulate_blobs(cameras, [frame.get(c.name, np.zeros((0, 2))) for c in cameras])
        if len(points) == 3:
            with contextlib.suppress(CalibrationError):
                found.append(order_lframe(np.array([p.point for p in points])))
    if not found:
        raise ValueError(f"{path}: no frame shows the L-frame's three spheres (a right angle, unequal arms) "
                         "to two or more cameras")
    corner, on_x, on_y = np.median(found, axis=0)
    print(f"floor frame from {len(found)} of {len(recorded.frames)} frames of {path}: corner "
          f"({corner[0]:+.4f}, {corner[1]:+.4f}, {corner[2]:+.4f}) m in the first camera's frame")
    return floor_frame(corner, on_x, on_y)


def _intrinsics(files: list[Path]) -> list[CameraModel]:
    """Cameras of rig files and camera_info files, in the order given."""
    import yaml

    from services.calibration.camera_info import read_camera_info
    from services.calibration.rig import read_rig

    cameras: list[CameraModel] = []
    for path in files:
        try:
            is_rig = isinstance(document := yaml.safe_load(path.read_text()), dict) and "cameras" in document
        except (OSError, yaml.YAMLError):
            is_rig = False  # read_camera_info names the problem
        cameras += read_rig(path).cameras if is_rig else [read_camera_info(path)]
    return cameras


def _calibrate_stereo(args: argparse.Namespace) -> int:
    import cv2

    from services.calibration.rig import write_rig
    from services.calibration.stereo import calibrate_stereo

    if len(args.images) != 2:
        raise ValueError(f"--stereo needs the images of two cameras (LEFT RIGHT), got {len(args.images)}")
    names = tuple(name.strip() for name in (args.names or "cam0,cam1").split(","))
    if len(names) != 2 or not all(names):
        raise ValueError(f"--names {args.names!r}: give two camera names, e.g. left,right")
    pattern = _calibration_pattern(args)
    first, second = (_image_files(where, args.glob) for where in args.images)
    both = sorted(set(first) & set(second))
    if both:
        raise ValueError(f"{both[0]} is an image of both cameras: give each camera its own images")
    if len(first) != len(second):
        raise ValueError(f"{len(first)} images of {names[0]} ({args.images[0]}) but {len(second)} of {names[1]} "
                         f"({args.images[1]}): images are paired in name order, one per camera and pair")
    if args.rig_frame not in (None, *names):
        raise ValueError(f"--rig-frame {args.rig_frame!r} is none of the cameras ({', '.join(names)})")
    result = calibrate_stereo([(path.name, cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)) for path in first],
                              [(path.name, cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)) for path in second],
                              pattern, (names[0], names[1]), refine_intrinsics=args.refine_intrinsics)
    print(result.report())
    try:
        write_rig(args.out, result.rig(args.out.stem, args.rig_frame))
    except OSError as exc:
        raise ValueError(f"cannot write {args.out}: {exc.strerror}") from exc
    print(f"wrote {args.out} (rig frame: {args.rig_frame or names[0]})")
    return 0


def add_calibrate(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("calibrate", help="camera intrinsics from photos of a chessboard or ChArUco board, "
                                         "written as ROS camera_info YAML (exit 2 if the photos cannot constrain "
                                         "them); with --stereo, two cameras and their relative pose, as a rig file; "
                                         "with --wand, a rig's extrinsics from a recorded wand, as a rig file")
    p.add_argument("images", nargs="*", metavar="DIR_OR_GLOB", help="a folder of images, or a quoted glob like "
                   "'data/left*.jpg'; with --stereo, one per camera (LEFT RIGHT), paired in name order")
    p.add_argument("--glob", default="*", metavar="PATTERN", help="in a folder, the files matching PATTERN (default *)")
    p.add_argument("--pattern", choices=("chessboard", "charuco"))
    p.add_argument("--size", metavar="COLSxROWS",
                   help="inner corners of a chessboard (e.g. 9x6), squares of a ChArUco board (e.g. 5x7)")
    p.add_argument("--square", type=float, metavar="M", help="side of a square, metres")
    p.add_argument("--marker", type=float, metavar="M", help="ChArUco: side of a marker, metres")
    p.add_argument("--dictionary", metavar="NAME", help="ChArUco: its markers' dictionary, e.g. DICT_6X6_250")
    p.add_argument("--camera", default="cam0", metavar="NAME", help="camera name written to the file (default cam0)")
    p.add_argument("-o", "--out", required=True, type=Path, metavar="CAMERA.yaml|RIG.yaml")
    add_force_option(p)
    p.add_argument("--wand", type=Path, metavar="RECORDING.mcap",
                   help="extrinsics from the IR images of a recording of a 3-sphere wand waved through the volume")
    p.add_argument("--wand-length", type=float, metavar="M", help="--wand: distance between its end spheres, metres")
    p.add_argument("--wand-middle", type=float, metavar="M",
                   help="--wand: distance of its middle sphere from one end, metres")
    p.add_argument("--intrinsics", nargs="+", type=Path, metavar="FILE",
                   help="--wand: rig or camera_info files of the cameras (default: the recording's camera_info)")
    p.add_argument("--floor", type=Path, metavar="LFRAME.mcap",
                   help="--wand: set the rig frame on an L-frame lying on the floor, recorded by the same cameras "
                        "(origin at its corner, x along its long arm, z up)")
    p.add_argument("--stereo", action="store_true", help="calibrate a stereo pair from image pairs: each camera's "
                   "intrinsics, then the pose between them (cv2.stereoCalibrate); --out is a rig file")
    p.add_argument("--names", metavar="A,B", help="--stereo: the two cameras' names (default cam0,cam1)")
    p.add_argument("--rig-frame", metavar="NAME", help="--stereo: the camera whose frame is the rig frame "
                   "(default the first)")
    p.add_argument("--refine-intrinsics", action="store_true", help="--stereo: let the stereo fit refine both "
                   "cameras' intrinsics (default: fixed at each camera's own calibration)")
    p.set_defaults(func=cmd_calibrate)
