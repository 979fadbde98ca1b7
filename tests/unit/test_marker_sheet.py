"""Printable marker sheets: true scale in PNG and PDF, boards whose files the marker tracker reads."""

from __future__ import annotations

import re
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest

from services.cli import PAPER_NAMES, main
from services.detection.markers.detector import MarkerDetector
from services.detection.markers.sheet import (
    INCH_M,
    PAPERS,
    board_document,
    charuco_sheet,
    draw_grid_board,
    grid_sheet,
    marker_sheet,
    parse_ids,
    write_pdf,
    write_png,
)
from services.estimation.markers.map import load_marker_map, parse_marker_map
from services.estimation.markers.pose import MarkerPoseEstimator

POINT_M = INCH_M / 72


def side_px(corners: np.ndarray) -> np.ndarray:
    """(N,) mean side length in px of (N, 4, 2) quads."""
    return np.linalg.norm(corners - np.roll(corners, -1, axis=1), axis=2).mean(axis=1)


def test_png_markers_have_their_true_size_at_the_stored_dpi(tmp_path):
    from PIL import Image

    length, dpi = 0.03, 300
    path = tmp_path / "sheet.png"
    write_png(marker_sheet(parse_ids("0,3,7-10"), "DICT_4X4_50", length), path, dpi)
    with Image.open(path) as stored:
        assert stored.info["dpi"] == pytest.approx((dpi, dpi), abs=0.01)
        assert stored.size == (round(PAPERS["a4"][0] / INCH_M * dpi), round(PAPERS["a4"][1] / INCH_M * dpi))
    found = MarkerDetector("DICT_4X4_50").detect(cv2.imread(str(path), cv2.IMREAD_GRAYSCALE))
    assert found.ids.tolist() == [0, 3, 7, 8, 9, 10]
    np.testing.assert_allclose(side_px(found.corners), length * dpi / INCH_M, atol=1.0)


def pdf_images_pt(path: Path) -> tuple[list[float], list[tuple[float, float]]]:
    """The PDF's MediaBox and the (width, height) in points of every image it places (its ``cm`` before ``Do``)."""
    data = path.read_bytes()
    box = [float(v) for v in re.search(rb"/MediaBox\s*\[([^\]]*)\]", data).group(1).split()]
    sizes = []
    for stream in re.finditer(rb"stream\r?\n(.*?)\r?\nendstream", data, re.S):
        try:
            content = zlib.decompress(stream.group(1))
        except zlib.error:
            continue
        for a, b, c, d in re.findall(rb"([-\d.]+)\s+([-\d.]+)\s+([-\d.]+)\s+([-\d.]+)\s+[-\d.]+\s+[-\d.]+\s+cm\s+"
                                     rb"/I\d+\s+Do", content):
            sizes.append((float(a), abs(float(d))))
            assert float(b) == 0 and float(c) == 0
    return box, sizes


@pytest.mark.parametrize("paper", ["a4", "letter"])
def test_pdf_page_is_the_paper_and_markers_are_placed_at_their_length(tmp_path, paper):
    length = 0.05
    path = tmp_path / "sheet.pdf"
    write_pdf(marker_sheet([1, 2, 3], "DICT_5X5_100", length, paper), path)
    box, sizes = pdf_images_pt(path)
    width, height = PAPERS[paper]
    assert box[:2] == [0, 0]
    assert box[2:] == pytest.approx([width / POINT_M, height / POINT_M], abs=0.01)
    assert paper != "letter" or box[2:] == pytest.approx([612, 792], abs=0.01)
    assert sizes == [pytest.approx((length / POINT_M, length / POINT_M), abs=0.01)] * 3


def fronto_pose(image: np.ndarray, document: dict, dictionary: str, pixels_per_m: float, distance: float):
    """The board pose from ``image`` read as a pinhole view at ``distance`` m straight onto the page; the
    board's centre at the image centre is what the map frame demands of a well drawn board."""
    marker_map = parse_marker_map(document, "board file")
    found = MarkerDetector(dictionary).detect(image)
    assert sorted(found.ids.tolist()) == sorted(marker_map.markers)
    centres = np.array([found.corners[n].mean(axis=0) for n in range(len(found))])
    positions = np.array([marker_map.markers[i].T_map_marker[:2, 3] for i in found.ids.tolist()])
    centre = (centres - positions * [pixels_per_m, -pixels_per_m]).mean(axis=0)
    focal = pixels_per_m * distance
    K = np.array([[focal, 0, centre[0]], [0, focal, centre[1]], [0, 0, 1]])
    estimate = MarkerPoseEstimator(marker_map=marker_map).estimate(found.ids, found.corners, found.side_m, K)
    return centres, positions, centre, estimate


@pytest.mark.parametrize("kind", ["grid", "charuco"])
def test_board_file_matches_the_drawn_board(tmp_path, kind):
    dpi, dictionary = 200, "DICT_6X6_250"
    if kind == "grid":
        sheet, board = grid_sheet(3, 4, 0.04, 0.01, dictionary, ids=range(10, 22))
    else:
        sheet, board = charuco_sheet(5, 7, 0.03, 0.015, dictionary)
    page = write_png(sheet, tmp_path / "board.png", dpi)
    pixels_per_m = dpi / INCH_M
    centres, positions, centre, estimate = fronto_pose(page, board_document(board, "table", dictionary), dictionary,
                                                       pixels_per_m, 1.0)
    residual = centres - centre - positions * [pixels_per_m, -pixels_per_m]
    assert np.abs(residual).max() < 1.0
    item = sheet.items[0]
    board_centre = np.array([item.x + item.width / 2, item.y + item.height / 2]) * pixels_per_m - 0.5
    np.testing.assert_allclose(centre, board_centre, atol=1.0)
    (pose,) = estimate.poses
    assert pose.target == "table"
    np.testing.assert_allclose(pose.T[:3, :3], np.diag([1.0, -1.0, -1.0]), atol=5e-3)  # 0.3 deg
    np.testing.assert_allclose(pose.T[:3, 3], [0, 0, 1.0], atol=2e-3)


def test_grid_board_drawing_matches_opencvs_where_opencv_draws_it():
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50)
    board = cv2.aruco.GridBoard((3, 4), 0.04, 0.01, dictionary)
    theirs = board.generateImage((700, 950), marginSize=0, borderBits=1)
    ours = draw_grid_board(board, 700, 950)
    assert ours.shape == theirs.shape
    assert np.mean(ours == theirs) > 0.995


def test_the_cli_writes_a_sheet_and_a_board_file_the_tracker_reads(tmp_path):
    out = tmp_path / "grid.png"
    assert main(["markers", "print", "-o", str(out), "--board", "grid", "--columns", "2", "--rows", "3",
                 "--length", "0.05", "--ids", "4-9", "--name", "desk"]) == 0
    loaded = load_marker_map(tmp_path / "grid.yaml")
    assert loaded.name == "desk" and loaded.dictionary == "DICT_4X4_50"
    assert sorted(loaded.markers) == [4, 5, 6, 7, 8, 9]
    assert {m.length for m in loaded.markers.values()} == {0.05}
    np.testing.assert_allclose(loaded.markers[4].T_map_marker[:3, 3], [-0.03125, 0.0625, 0.0])


def test_the_cli_keeps_an_existing_sheet_or_board_file_unless_forced(tmp_path, capsys):
    out, board_file = tmp_path / "grid.png", tmp_path / "grid.yaml"
    grid = ["markers", "print", "-o", str(out), "--board", "grid", "--columns", "2", "--rows", "3", "--length", "0.05"]
    board_file.write_text("mine\n")
    assert main(grid) == 2
    assert capsys.readouterr().err.strip().endswith(f"{board_file} exists: give --force to overwrite it")
    assert not out.exists() and board_file.read_text() == "mine\n"  # refused before the sheet was written
    assert main([*grid, "--force"]) == 0 and load_marker_map(board_file).name == "board"
    assert main(grid) == 2
    assert f"{out} exists" in capsys.readouterr().err


def test_bad_sheets_are_refused_in_one_line(tmp_path, capsys):
    with pytest.raises(ValueError, match=r"^id 50 is not in DICT_4X4_50 \(ids 0 to 49\)$"):
        marker_sheet([3, 50], "DICT_4X4_50", 0.05)
    with pytest.raises(ValueError, match="given more than once"):
        marker_sheet([3, 3], "DICT_4X4_50", 0.05)
    with pytest.raises(ValueError, match=r"'4-x' is not an id"):
        parse_ids("1,4-x")
    with pytest.raises(ValueError, match=r"largest --length that fits is (0\.\d+) m") as refused:
        marker_sheet(list(range(20)), "DICT_4X4_50", 0.06)
    largest = float(re.search(r"is (0\.\d+) m", str(refused.value)).group(1))
    assert len(marker_sheet(list(range(20)), "DICT_4X4_50", largest).items) == 20
    with pytest.raises(ValueError, match="too big"):
        marker_sheet(list(range(20)), "DICT_4X4_50", largest + 0.0001)
    with pytest.raises(ValueError, match=r"largest --length that fits is 0\.0161 m"):
        charuco_sheet(5, 7, 0.04, 0.02, "DICT_6X6_250")
    with pytest.raises(ValueError, match="give 12 ids, got 2"):
        grid_sheet(3, 4, 0.02, 0.005, "DICT_4X4_50", ids=[0, 1])
    assert main(["markers", "print", "-o", str(tmp_path / "x.png"), "--ids", "0-60", "--length", "0.02"]) == 2
    err = capsys.readouterr().err
    assert "id 50 is not in DICT_4X4_50" in err and "Traceback" not in err
    assert main(["markers", "print", "-o", str(tmp_path / "x.jpg"), "--length", "0.02"]) == 2
    assert not (tmp_path / "x.png").exists()


def test_the_cli_offers_every_paper():
    assert tuple(PAPERS) == PAPER_NAMES
