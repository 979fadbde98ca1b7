"""Printable sheets of markers and marker boards, laid out at true scale on one page.

A sheet is one page of paper (``PAPERS``: A4 by default, US letter, A3) holding either single
markers or one board, every length in metres on the paper:

* single markers (``marker_sheet``): markers of side ``length`` (the black square, border
  included) in rows from the top left, each with a white quiet zone of ``quiet_zone(length,
  bits)`` (two marker cells, at least ``MIN_QUIET_M``) on every side, and its id and dictionary
  written small under it;
* a board (``grid_sheet``: OpenCV's ``GridBoard``, ``charuco_sheet``: its ``CharucoBoard``),
  centred, with the same quiet zone around it and a line naming it.

Every page has a header (print at 100 %, no fit to page) and a scale bar of ``SCALE_BAR_M``
to measure once printed. The page frame: origin at the page's top-left corner, x right, y down,
metres. Markers are drawn by ``cv2.aruco.generateImageMarker``, ChArUco boards by their
``generateImage`` and grid boards marker by marker (``draw_grid_board``); ``render_page``
rasterises a sheet at a given dpi (each item's pixel size is its length in inches times the
dpi, rounded), ``write_png`` stores the dpi in the
file (Pillow, pHYs chunk) so it prints at true size, and ``write_pdf`` (matplotlib, the
``plot`` extra) places each item's image at its exact size on a page of the paper's size.

``board_document`` is a board's marker map file (the ``services.estimation.markers.map`` layout)
in the map frame that reader uses: origin at the board's centre, x right, y up, z out of the board; each
marker's position is the centre of the square OpenCV draws it in. A sheet that cannot be
printed (an id outside the dictionary, a size that does not fit the paper) raises
ValueError in one line, naming the largest size that fits when that is what is wrong.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from services.detection.markers.detector import aruco_dictionary

PAPERS: dict[str, tuple[float, float]] = {"a4": (0.210, 0.297), "letter": (0.2159, 0.2794), "a3": (0.297, 0.420)}
"""Paper name -> (width, height) in metres, portrait."""
MARGIN_M = 0.010
"""Unprinted border of the page (most printers cannot print closer to the edge)."""
HEADER_M = 0.014
FOOTER_M = 0.016
LABEL_M = 0.005
"""Height of the band under a marker or board that holds its label."""
MIN_QUIET_M = 0.005
SCALE_BAR_M = 0.100
SCALE_BAR_HEIGHT_M = 0.004
TEXT_M = 0.0025
"""Height of small text (about 7 pt)."""
INCH_M = 0.0254
POINT_M = INCH_M / 72


@dataclass(frozen=True)
class Item:
    """One drawn thing on the page: its top-left corner ``x``, ``y`` and size ``width`` x ``height``
    (metres, page frame), ``label`` written under it, and ``draw(width_px, height_px)`` giving its
    (height_px, width_px) uint8 image, black on white."""

    x: float
    y: float
    width: float
    height: float
    label: str
    draw: Callable[[int, int], np.ndarray]


@dataclass(frozen=True)
class Sheet:
    """A page: ``paper`` (name of ``PAPERS``), its ``items``, the ``title`` line of its header."""

    paper: str
    items: tuple[Item, ...]
    title: str

    @property
    def size(self) -> tuple[float, float]:
        """(width, height) of the page, metres."""
        return PAPERS[self.paper]


def paper_size(paper: str) -> tuple[float, float]:
    """(width, height) of ``paper`` in metres; ValueError names the known papers."""
    if paper not in PAPERS:
        raise ValueError(f"unknown paper {paper!r}: use one of {', '.join(PAPERS)}")
    return PAPERS[paper]


def quiet_zone(length: float, bits: int) -> float:
    """White margin (m) a marker of side ``length`` with ``bits`` x ``bits`` inner cells keeps on each side:
    two of its cells (a one-cell black border is drawn around the bits), at least ``MIN_QUIET_M``."""
    return max(2 * length / (bits + 2), MIN_QUIET_M)


def parse_ids(text: str) -> list[int]:
    """Ids of ``text``: comma-separated ids and inclusive ranges, e.g. ``0,3,5-8``; ValueError names a bad part."""
    ids: list[int] = []
    for part in text.split(","):
        first, dash, last = part.strip().partition("-")
        if not first.isdigit() or (dash and not last.isdigit()):
            raise ValueError(f"--ids {text!r}: {part.strip()!r} is not an id or a range like 0-5")
        low, high = int(first), int(last) if dash else int(first)
        if high < low:
            raise ValueError(f"--ids {text!r}: range {part.strip()} runs backwards")
        ids.extend(range(low, high + 1))
    return ids


def check_ids(ids: Sequence[int], dictionary: str) -> cv2.aruco.Dictionary:
    """The dictionary named ``dictionary`` once every id of ``ids`` exists in it, once; ValueError otherwise."""
    aruco = aruco_dictionary(dictionary)
    size = len(aruco.bytesList)
    if not ids:
        raise ValueError("no marker ids given")
    outside = [i for i in ids if not 0 <= i < size]
    if outside:
        raise ValueError(f"id {outside[0]} is not in {dictionary} (ids 0 to {size - 1})")
    twice = sorted({i for i in ids if list(ids).count(i) > 1})
    if twice:
        raise ValueError(f"id {twice[0]} is given more than once")
    return aruco


def _printable(paper: str) -> tuple[float, float, float, float]:
    """(left, top, width, height) of the area items may use, metres, page frame."""
    width, height = paper_size(paper)
    return MARGIN_M, MARGIN_M + HEADER_M, width - 2 * MARGIN_M, height - 2 * MARGIN_M - HEADER_M - FOOTER_M


def _marker_items(ids: Sequence[int], dictionary: str, aruco: cv2.aruco.Dictionary, length: float,
                  paper: str) -> tuple[Item, ...] | None:
    """Single markers laid out in rows on ``paper``, or None when they do not all fit."""
    left, top, width, height = _printable(paper)
    quiet = quiet_zone(length, aruco.markerSize)
    columns = math.floor((width - quiet) / (length + quiet) + 1e-9)
    rows = math.floor((height - quiet) / (length + LABEL_M + quiet) + 1e-9)
    if columns < 1 or rows < 1 or len(ids) > columns * rows:
        return None
    items = []
    for n, marker_id in enumerate(ids):
        row, column = divmod(n, columns)
        items.append(Item(left + quiet + column * (length + quiet), top + quiet + row * (length + LABEL_M + quiet),
                          length, length, f"id {marker_id}  {dictionary}", _marker_drawing(aruco, marker_id)))
    return tuple(items)


def _marker_drawing(aruco: cv2.aruco.Dictionary, marker_id: int) -> Callable[[int, int], np.ndarray]:
    def draw(width_px: int, height_px: int) -> np.ndarray:
        return cv2.aruco.generateImageMarker(aruco, marker_id, width_px, borderBits=1)
    return draw


def draw_grid_board(board: cv2.aruco.GridBoard, width_px: int, height_px: int) -> np.ndarray:
    """(height_px, width_px) uint8 image of ``board`` filling it, markers placed from its object points.

    What ``GridBoard.generateImage(size, marginSize=0, borderBits=1)`` draws, but at every size: OpenCV
    5.0's fails its ROI assertion at some (e.g. a 3x4 board at 1654 x 2244 px)."""
    image = np.full((height_px, width_px), 255, np.uint8)
    corners = [np.asarray(c, np.float64).reshape(4, 3) for c in board.getObjPoints()]
    every = np.concatenate(corners)
    origin, extent = every.min(axis=0), every.max(axis=0) - every.min(axis=0)
    scale = min(width_px / extent[0], height_px / extent[1])
    for marker_id, square in zip(np.asarray(board.getIds()).reshape(-1).tolist(), corners, strict=True):
        left, top = np.rint((square.min(axis=0) - origin)[:2] * scale).astype(int)
        right, bottom = np.rint((square.max(axis=0) - origin)[:2] * scale).astype(int)
        side = min(right - left, bottom - top)
        image[top:top + side, left:left + side] = cv2.aruco.generateImageMarker(board.getDictionary(), marker_id,
                                                                                side, borderBits=1)
    return image


def _board_item(board: cv2.aruco.Board, extent: tuple[float, float], quiet: float, label: str,
                paper: str) -> tuple[Item, ...] | None:
    """A board of ``extent`` (width, height) m centred on ``paper``, or None when it does not fit."""
    left, top, width, height = _printable(paper)
    if extent[0] + 2 * quiet > width + 1e-9 or extent[1] + LABEL_M + 2 * quiet > height + 1e-9:
        return None
    x = left + (width - extent[0]) / 2
    y = top + (height - extent[1] - LABEL_M) / 2
    if isinstance(board, cv2.aruco.GridBoard):
        return (Item(x, y, extent[0], extent[1], label, lambda w, h: draw_grid_board(board, w, h)),)
    return (Item(x, y, extent[0], extent[1], label,
                 lambda w, h: board.generateImage((w, h), marginSize=0, borderBits=1)),)


def _largest(fits: Callable[[float], bool], high: float) -> float:
    """The largest length <= ``high`` (m, to 0.1 mm) for which ``fits`` holds, 0 if none; ``fits`` must be
    monotone (true below some length, false above)."""
    low_mm, high_mm = 0, int(high * 10000)
    while low_mm < high_mm:
        mid = (low_mm + high_mm + 1) // 2
        if fits(mid / 10000):
            low_mm = mid
        else:
            high_mm = mid - 1
    return low_mm / 10000


def _too_big(what: str, paper: str, largest: float) -> ValueError:
    if largest <= 0:
        return ValueError(f"{what}: too many for one {paper} page at any size")
    return ValueError(f"{what}: too big for one {paper} page; the largest --length that fits is "
                      f"{largest:.4f} m ({largest * 1000:.1f} mm)")


def _positive(name: str, value: float) -> None:
    if not (math.isfinite(value) and value > 0):
        raise ValueError(f"{name} must be a length in metres > 0, got {value}")


def marker_sheet(ids: Sequence[int], dictionary: str, length: float, paper: str = "a4") -> Sheet:
    """A sheet of single markers ``ids`` of ``dictionary``, each ``length`` m wide."""
    _positive("--length", length)
    paper_size(paper)
    aruco = check_ids(ids, dictionary)
    items = _marker_items(ids, dictionary, aruco, length, paper)
    if items is None:
        largest = _largest(lambda s: _marker_items(ids, dictionary, aruco, s, paper) is not None, length)
        raise _too_big(f"{len(ids)} marker(s) of {length * 1000:.1f} mm", paper, largest)
    return Sheet(paper, items, f"{dictionary} markers, side {length * 1000:.1f} mm (black square)")


def _board_ids(ids: Sequence[int] | None, count: int, dictionary: str) -> list[int]:
    chosen = list(range(count)) if ids is None else list(ids)
    if len(chosen) != count:
        raise ValueError(f"the board holds {count} markers: give {count} ids, got {len(chosen)}")
    check_ids(chosen, dictionary)
    return chosen


def grid_sheet(columns: int, rows: int, length: float, separation: float, dictionary: str,
               ids: Sequence[int] | None = None, paper: str = "a4") -> tuple[Sheet, cv2.aruco.GridBoard]:
    """A sheet of an ArUco grid board of ``columns`` x ``rows`` markers of side ``length`` m, ``separation`` m
    apart, ids ``ids`` (default 0, 1, ...) row by row from the top left; and the board."""
    _positive("--length", length)
    _positive("--separation", separation)
    if columns < 1 or rows < 1:
        raise ValueError(f"a grid board needs at least 1x1 markers, got {columns}x{rows}")
    chosen = _board_ids(ids, columns * rows, dictionary)
    aruco = aruco_dictionary(dictionary)

    def lay_out(scale: float) -> tuple[Item, ...] | None:
        board = cv2.aruco.GridBoard((columns, rows), length * scale, separation * scale, aruco,
                                    np.array(chosen, np.int32))
        extent = (columns * length + (columns - 1) * separation) * scale, \
                 (rows * length + (rows - 1) * separation) * scale
        label = (f"grid board {columns}x{rows}, markers {length * scale * 1000:.1f} mm, gap "
                 f"{separation * scale * 1000:.1f} mm, {dictionary}, ids {chosen[0]}..{chosen[-1]}")
        return _board_item(board, extent, quiet_zone(length * scale, aruco.markerSize), label, paper)

    items = lay_out(1.0)
    if items is None:
        largest = _largest(lambda s: lay_out(s / length) is not None, length)
        raise _too_big(f"a {columns}x{rows} grid board with {length * 1000:.1f} mm markers "
                       f"(gap scaled alike)", paper, largest)
    board = cv2.aruco.GridBoard((columns, rows), length, separation, aruco, np.array(chosen, np.int32))
    return Sheet(paper, items, items[0].label), board


def charuco_sheet(columns: int, rows: int, square: float, length: float, dictionary: str,
                  ids: Sequence[int] | None = None, paper: str = "a4") -> tuple[Sheet, cv2.aruco.CharucoBoard]:
    """A sheet of a ChArUco board of ``columns`` x ``rows`` squares of ``square`` m with markers of ``length`` m
    (OpenCV's layout, its ids ``ids``, default 0, 1, ...); and the board."""
    _positive("--square", square)
    _positive("--length", length)
    if columns < 2 or rows < 2 or length >= square:
        raise ValueError(f"a ChArUco board needs at least 2x2 squares and --length < --square, got "
                         f"{columns}x{rows}, square {square} m, marker {length} m")
    aruco = aruco_dictionary(dictionary)
    count = len(cv2.aruco.CharucoBoard((columns, rows), square, length, aruco).getIds())
    chosen = _board_ids(ids, count, dictionary)

    def board_at(scale: float) -> cv2.aruco.CharucoBoard:
        return cv2.aruco.CharucoBoard((columns, rows), square * scale, length * scale, aruco,
                                      np.array(chosen, np.int32))

    def lay_out(scale: float) -> tuple[Item, ...] | None:
        label = (f"ChArUco board {columns}x{rows} squares of {square * scale * 1000:.1f} mm, markers "
                 f"{length * scale * 1000:.1f} mm, {dictionary}")
        return _board_item(board_at(scale), (columns * square * scale, rows * square * scale),
                           quiet_zone(square * scale, aruco.markerSize), label, paper)

    items = lay_out(1.0)
    if items is None:
        largest = _largest(lambda s: lay_out(s / length) is not None, length)
        raise _too_big(f"a {columns}x{rows} ChArUco board with {length * 1000:.1f} mm markers "
                       f"(squares scaled alike)", paper, largest)
    return Sheet(paper, items, items[0].label), board_at(1.0)


def board_document(board: cv2.aruco.Board, name: str, dictionary: str) -> dict:
    """``board`` as the YAML document ``services.estimation.markers.map.load_marker_map`` reads: an explicit
    ``markers`` list in the map frame (origin at the board's centre, x right, y up, z out of the board)."""
    corners = [np.asarray(c, np.float64).reshape(4, 3) for c in board.getObjPoints()]
    ids = np.asarray(board.getIds()).reshape(-1).tolist()
    every = np.concatenate(corners)
    middle = (every.min(axis=0) + every.max(axis=0)) / 2
    if isinstance(board, cv2.aruco.CharucoBoard):
        columns, rows = board.getChessboardSize()
        middle = np.array([columns, rows, 0.0]) * board.getSquareLength() / 2
    markers = []
    for marker_id, square in zip(ids, corners, strict=True):
        centre = square.mean(axis=0) - middle  # OpenCV's board frame: y down, so y flips
        markers.append({"id": int(marker_id), "length": round(float(np.linalg.norm(square[1] - square[0])), 6),
                        "position": [round(float(centre[0]), 6), round(float(-centre[1]), 6), 0.0],
                        "quaternion": [0.0, 0.0, 0.0, 1.0]})
    return {"name": name, "dictionary": dictionary, "markers": markers}


def pixels(length: float, dpi: float) -> int:
    """``length`` metres as a whole number of pixels at ``dpi``."""
    return round(length / INCH_M * dpi)


def _text(image: np.ndarray, text: str, x: int, baseline: int, height_px: int) -> None:
    """Write ``text`` in black into ``image`` with its left end at ``x`` and its baseline at ``baseline``, about
    ``height_px`` tall (capital letters)."""
    font = cv2.FONT_HERSHEY_SIMPLEX
    scale = height_px / cv2.getTextSize("H", font, 1.0, 1)[0][1]
    cv2.putText(image, text, (x, baseline), font, scale, 0, max(1, round(scale * 1.5)), cv2.LINE_AA)


def header_lines(sheet: Sheet) -> tuple[str, str]:
    """The two lines at the top of a page."""
    return ("PRINT AT 100 % (actual size): no 'fit to page', no scaling. Check the scale bar below.", sheet.title)


def scale_bar_label() -> str:
    return f"scale bar: {SCALE_BAR_M * 1000:.0f} mm when printed right"


def render_page(sheet: Sheet, dpi: float = 300) -> np.ndarray:
    """(H, W) uint8 image of the whole page at ``dpi``, white paper, black ink."""
    if not (math.isfinite(dpi) and dpi >= 72):
        raise ValueError(f"--dpi must be at least 72, got {dpi}")
    width, height = sheet.size
    page = np.full((pixels(height, dpi), pixels(width, dpi)), 255, np.uint8)
    text_px = max(pixels(TEXT_M, dpi), 6)
    first, second = header_lines(sheet)
    _text(page, first, pixels(MARGIN_M, dpi), pixels(MARGIN_M + 0.004, dpi), text_px)
    _text(page, second, pixels(MARGIN_M, dpi), pixels(MARGIN_M + 0.009, dpi), text_px)
    for item in sheet.items:
        left, top = pixels(item.x, dpi), pixels(item.y, dpi)
        width_px, height_px = pixels(item.width, dpi), pixels(item.height, dpi)
        page[top:top + height_px, left:left + width_px] = item.draw(width_px, height_px)
        _text(page, item.label, left, pixels(item.y + item.height + 0.001 + TEXT_M, dpi), text_px)
    bar = _scale_bar(sheet)
    for x, y, w, h, black in bar:
        x0, y0, x1, y1 = pixels(x, dpi), pixels(y, dpi), pixels(x + w, dpi), pixels(y + h, dpi)
        page[y0:y1, x0:x1] = 0 if black else 255
        cv2.rectangle(page, (x0, y0), (x1 - 1, y1 - 1), 0, 1)
    _text(page, scale_bar_label(), pixels(bar[0][0], dpi), pixels(bar[0][1] + bar[0][3] + 0.002 + TEXT_M, dpi),
          text_px)
    return page


def _scale_bar(sheet: Sheet) -> list[tuple[float, float, float, float, bool]]:
    """The scale bar's ten 1 cm segments (x, y, width, height m, page frame; black or white), bottom left."""
    top = sheet.size[1] - MARGIN_M - FOOTER_M + 0.003
    segment = SCALE_BAR_M / 10
    return [(MARGIN_M + n * segment, top, segment, SCALE_BAR_HEIGHT_M, n % 2 == 0) for n in range(10)]


def write_png(sheet: Sheet, path: str | Path, dpi: float = 300) -> np.ndarray:
    """Write the page at ``dpi`` as a greyscale PNG whose pHYs chunk holds the dpi; return the image."""
    from PIL import Image

    page = render_page(sheet, dpi)
    Image.fromarray(page).save(str(path), format="PNG", dpi=(dpi, dpi))
    return page


def write_pdf(sheet: Sheet, path: str | Path, dpi: float = 300) -> None:
    """Write the page as a one-page PDF of the paper's size, each item's image (drawn at ``dpi``) placed at its
    exact size, text and scale bar as vectors."""
    from matplotlib.figure import Figure
    from matplotlib.patches import Rectangle

    width, height = sheet.size
    figure = Figure(figsize=(width / INCH_M, height / INCH_M))
    font_pt = TEXT_M / POINT_M * 1.35

    def at(x: float, y: float, w: float = 0.0, h: float = 0.0) -> tuple[float, float, float, float]:
        """Figure fractions (left, bottom, width, height) of a box given in the page frame."""
        return x / width, 1 - (y + h) / height, w / width, h / height

    for n, line in enumerate(header_lines(sheet)):
        figure.text(*at(MARGIN_M, MARGIN_M + 0.004 + n * 0.005)[:2], line, fontsize=font_pt, va="baseline")
    for item in sheet.items:
        axes = figure.add_axes(at(item.x, item.y, item.width, item.height))
        axes.imshow(item.draw(pixels(item.width, dpi), pixels(item.height, dpi)), cmap="gray", vmin=0, vmax=255,
                    interpolation="none", aspect="auto")
        axes.set_axis_off()
        figure.text(*at(item.x, item.y + item.height + 0.001 + TEXT_M)[:2], item.label, fontsize=font_pt,
                    va="baseline")
    for x, y, w, h, black in _scale_bar(sheet):
        figure.add_artist(Rectangle(at(x, y, w, h)[:2], w / width, h / height, transform=figure.transFigure,
                                    facecolor="black" if black else "white", edgecolor="black", linewidth=0.3))
    x, y, _, h, _ = _scale_bar(sheet)[0]
    figure.text(*at(x, y + h + 0.002 + TEXT_M)[:2], scale_bar_label(), fontsize=font_pt, va="baseline")
    figure.savefig(str(path), format="pdf")
