"""``artrack markers print``: printable sheets of markers or of a board, at true scale."""

from __future__ import annotations

import argparse
from pathlib import Path

from services.cli.outputs import add_force_option
from services.runtime.outputs import check_output

PAPER_NAMES = ("a4", "letter", "a3")
"""``artrack markers print --paper`` choices: ``marker_sheet.PAPERS``' names (that module loads OpenCV)."""


def cmd_markers_print(args: argparse.Namespace) -> int:
    import cv2
    import yaml

    from services.detection.markers.settings import DEFAULT_DICTIONARY
    from services.detection.markers.sheet import (
        PAPERS,
        Sheet,
        board_document,
        charuco_sheet,
        grid_sheet,
        marker_sheet,
        parse_ids,
        write_pdf,
        write_png,
    )

    suffix = args.out.suffix.lower()
    if args.paper not in PAPERS:
        raise ValueError(f"--paper {args.paper}: use one of {', '.join(PAPERS)}")
    dictionary = args.dictionary or DEFAULT_DICTIONARY
    if suffix not in (".pdf", ".png"):
        raise ValueError(f"-o {args.out}: give a .pdf or .png file")
    board_file = args.board_file or args.out.with_suffix(".yaml")
    for output in (args.out, board_file) if args.board is not None else (args.out,):
        check_output(output, args.force)
    ids = parse_ids(args.ids) if args.ids is not None else None
    sheet: Sheet
    board: cv2.aruco.Board | None = None
    if args.board is None:
        sheet = marker_sheet(ids if ids is not None else [0], dictionary, args.length, args.paper)
    elif args.columns is None or args.rows is None:
        raise ValueError(f"--board {args.board} needs --columns and --rows")
    elif args.board == "grid":
        separation = args.separation if args.separation is not None else args.length / 4
        sheet, board = grid_sheet(args.columns, args.rows, args.length, separation, dictionary, ids, args.paper)
    elif args.square is None:
        raise ValueError("--board charuco needs --square (the side of a chessboard square, metres)")
    else:
        sheet, board = charuco_sheet(args.columns, args.rows, args.square, args.length, dictionary, ids,
                                     args.paper)
    try:
        (write_pdf if suffix == ".pdf" else write_png)(sheet, args.out, args.dpi)
    except OSError as exc:
        raise ValueError(f"cannot write {args.out}: {exc.strerror}") from exc
    print(f"wrote {args.out} ({args.paper}): print it at 100 % (actual size), then measure the scale bar")
    if board is not None:
        try:
            board_file.write_text(yaml.safe_dump(board_document(board, args.name, dictionary), sort_keys=False,
                                                default_flow_style=None))
        except OSError as exc:
            raise ValueError(f"cannot write {board_file}: {exc.strerror}") from exc
        print(f"wrote {board_file}: pass it to `artrack run marker --board {board_file}`")
    return 0


def add_markers(sub: argparse._SubParsersAction) -> None:
    markers = sub.add_parser("markers", help="marker utilities: `artrack markers print` draws printable sheets")
    markers_sub = markers.add_subparsers(dest="markers_command", required=True, metavar="ACTION")
    p = markers_sub.add_parser("print", help="a page of markers or a board at true scale (PDF or PNG), with the "
                               "board file the marker tracker reads")
    p.add_argument("-o", "--out", required=True, type=Path, metavar="SHEET.pdf|SHEET.png")
    p.add_argument("--dictionary", metavar="NAME", help="cv2.aruco dictionary (default: the marker tracker's, "
                   "DICT_4X4_50)")
    p.add_argument("--ids", metavar="LIST", help="ids and ranges, e.g. 0,1,2 or 0-5 (default 0; a board: 0, 1, ...)")
    p.add_argument("--length", required=True, type=float, metavar="M",
                   help="side of each marker's black square when printed, metres")
    p.add_argument("--paper", default="a4", choices=PAPER_NAMES, help="paper size (default a4)")
    p.add_argument("--dpi", type=float, default=300, help="PNG resolution, stored in the file; PDF: resolution "
                   "of the marker images placed at their exact size (default 300)")
    p.add_argument("--board", choices=("grid", "charuco"), help="one board instead of single markers: an ArUco "
                   "grid board or a ChArUco board")
    p.add_argument("--columns", type=int, metavar="N", help="board: markers (grid) or squares (charuco) per row")
    p.add_argument("--rows", type=int, metavar="N", help="board: rows of markers (grid) or squares (charuco)")
    p.add_argument("--separation", type=float, metavar="M", help="grid: gap between markers, metres "
                   "(default a quarter of --length)")
    p.add_argument("--square", type=float, metavar="M", help="charuco: side of a chessboard square, metres")
    p.add_argument("--name", default="board", help="board: its name, the pose key's last part (default board)")
    p.add_argument("--board-file", type=Path, metavar="BOARD.yaml", help="board: where its marker map goes "
                   "(default: beside the sheet, .yaml)")
    add_force_option(p)
    p.set_defaults(func=cmd_markers_print)
