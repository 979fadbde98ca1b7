"""MarkerDetector: ids, corners, quality and side lengths on rendered markers; dictionaries and settings."""

import cv2
import numpy as np
import pytest

from services.detection.markers.detector import DICTIONARY_NAMES, MarkerDetector, aruco_dictionary, to_grey
from services.geometry.camera import project_points
from services.geometry.se3 import transform_points
from services.synthetic import make_scene
from services.synthetic.plane import rectangle_corners

CELL_PX = 30


def marker_image(dictionary, marker_id: int, top: int = 100, left: int = 200) -> np.ndarray:
    """A 480x640 white image holding one marker of ``CELL_PX`` px per cell at (top, left)."""
    side = (dictionary.markerSize + 2) * CELL_PX
    image = np.full((480, 640), 255, np.uint8)
    image[top:top + side, left:left + side] = cv2.aruco.generateImageMarker(dictionary, marker_id, side)
    return image


def truth_corners(frame, scene) -> dict[int, np.ndarray]:
    """Marker id -> (4, 2) projected corners of the markers the scene's ground truth lists."""
    L = scene.marker_length
    out = {}
    for _, child, T_cam_marker in frame.truth["cam0"]:
        out[int(child.split("/")[1])] = project_points(transform_points(T_cam_marker, rectangle_corners(L, L)),
                                                       scene.cameras[0].K)
    return out


def test_scene_markers_are_found_sorted_with_their_corners_and_lengths():
    scene = make_scene("markers", ids=(9, 3, 41, 0, 17, 28))
    detector = MarkerDetector("DICT_4X4_50", marker_length=0.05, lengths={41: 0.08})
    seen = 0
    for index in range(0, 600, 60):
        frame = scene.render(index)
        found = detector.detect(frame.images["cam0"])
        truth = truth_corners(frame, scene)
        assert found.ids.dtype == np.int32 and found.corners.dtype == np.float32
        assert found.corners.shape == (len(found), 4, 2) and found.quality.shape == found.side_m.shape == (len(found),)
        assert list(found.ids) == sorted(found.ids) and set(found.ids) <= set(truth)
        for marker_id, corners, side in zip(found.ids, found.corners, found.side_m, strict=True):
            assert np.abs(corners - truth[marker_id]).max() < 1.0, (index, marker_id)
            assert side == pytest.approx(0.08 if marker_id == 41 else 0.05)
        assert np.all((found.quality > 0.8) & (found.quality <= 1.0))
        seen += len(found)
    assert seen >= 40


def test_quality_loses_one_cell_share_per_cell_of_the_wrong_colour():
    for name in ("DICT_4X4_50", "DICT_6X6_250"):
        detector = MarkerDetector(name, parameters={"errorCorrectionRate": 1.0})
        cells = detector.dictionary.markerSize + 2
        clean = marker_image(detector.dictionary, 7)
        flipped = clean.copy()
        top, left = 100 + 2 * CELL_PX, 200 + 2 * CELL_PX  # an inner cell
        flipped[top:top + CELL_PX, left:left + CELL_PX] = 255 - clean[top + CELL_PX // 2, left + CELL_PX // 2]
        before, after = detector.detect(clean), detector.detect(flipped)
        assert list(before.ids) == list(after.ids) == [7]
        assert before.quality[0] == pytest.approx(1.0)
        assert before.quality[0] - after.quality[0] == pytest.approx(1 / cells**2, abs=1e-3)


def test_heavy_noise_lowers_quality():
    detector = MarkerDetector("DICT_4X4_50")
    clean = marker_image(detector.dictionary, 3)
    noisy = np.clip(clean + np.random.default_rng(0).normal(0, 40, clean.shape), 0, 255).astype(np.uint8)
    assert detector.detect(clean).quality[0] == pytest.approx(1.0)
    assert 0.5 < detector.detect(noisy).quality[0] < 0.95


def test_every_encoding_gives_the_same_detections():
    detector = MarkerDetector("DICT_5X5_100", marker_length=0.1)
    mono = cv2.GaussianBlur(marker_image(detector.dictionary, 12), (0, 0), 1.0)
    reference = detector.detect(mono)
    assert list(reference.ids) == [12]
    encoded = {
        "bgr8": cv2.cvtColor(mono, cv2.COLOR_GRAY2BGR),
        "bgra8": cv2.cvtColor(mono, cv2.COLOR_GRAY2BGRA),
        "mono16": (mono.astype(np.uint16) * 16 + 1000),  # 12-bit data in 16 bits
    }
    for name, image in encoded.items():
        assert np.array_equal(to_grey(image), mono), name
        found = detector.detect(image)
        assert np.array_equal(found.ids, reference.ids) and np.array_equal(found.corners, reference.corners), name
    with pytest.raises(ValueError, match="mono8, bgr8, bgra8 or mono16"):
        detector.detect(mono.astype(np.float32))


def test_nothing_found_gives_empty_typed_arrays():
    found = MarkerDetector("DICT_4X4_50").detect(np.full((120, 160), 128, np.uint8))
    assert len(found) == 0
    assert (found.ids.shape, found.corners.shape, found.quality.shape, found.side_m.shape) == ((0,), (0, 4, 2),
                                                                                               (0,), (0,))
    assert (found.ids.dtype, found.corners.dtype) == (np.int32, np.float32)


def test_the_same_id_twice_comes_in_a_fixed_order():
    dictionary = aruco_dictionary("DICT_4X4_50")
    image = np.minimum(marker_image(dictionary, 5, top=40, left=360), marker_image(dictionary, 5, top=250, left=40))
    found = MarkerDetector(dictionary).detect(image)
    assert list(found.ids) == [5, 5]
    assert found.corners[0, 0, 0] < found.corners[1, 0, 0]


@pytest.mark.parametrize("refinement", ["lines", "none", "subpix", "contour", "apriltag"])
def test_every_refinement_finds_the_corners(refinement):
    detector = MarkerDetector("DICT_APRILTAG_36h11", refinement=refinement)
    image = marker_image(detector.dictionary, 21)
    side = (detector.dictionary.markerSize + 2) * CELL_PX
    expected = np.array([[200, 100], [200 + side, 100], [200 + side, 100 + side], [200, 100 + side]]) - 0.5
    found = detector.detect(image)
    assert list(found.ids) == [21]
    assert np.abs(found.corners[0] - expected).max() < 1.0


def test_every_predefined_name_loads():
    for name in ("DICT_4X4_50", "DICT_7X7_1000", "DICT_ARUCO_ORIGINAL", "DICT_APRILTAG_16h5", "DICT_APRILTAG_25h9",
                 "DICT_APRILTAG_36h10", "DICT_APRILTAG_36h11", "DICT_ARUCO_MIP_36h12"):
        assert name in DICTIONARY_NAMES
    sizes = {name: aruco_dictionary(name).markerSize for name in DICTIONARY_NAMES}
    assert sizes["DICT_4X4_50"] == 4 and sizes["DICT_APRILTAG_36h11"] == 6 and sizes["DICT_ARUCO_MIP_36h12"] == 6


def test_a_custom_dictionary_file_round_trips(tmp_path):
    custom = cv2.aruco.extendDictionary(12, 5, randomSeed=3)
    path = tmp_path / "custom.yml"
    storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    custom.writeDictionary(storage)
    storage.release()
    loaded = aruco_dictionary(str(path))
    assert loaded.markerSize == 5 and np.array_equal(loaded.bytesList, custom.bytesList)
    assert list(MarkerDetector(path).detect(marker_image(custom, 11)).ids) == [11]


def test_bad_dictionaries_are_refused_with_a_reason(tmp_path):
    with pytest.raises(ValueError, match="unknown marker dictionary 'DICT_5X5_2'.*DICT_4X4_50.*DICT_APRILTAG_36h11"):
        aruco_dictionary("DICT_5X5_2")
    with pytest.raises(ValueError, match="does not exist"):
        aruco_dictionary(str(tmp_path / "missing.yml"))
    (tmp_path / "camera.yml").write_text("%YAML:1.0\nimage_width: 640\n")
    with pytest.raises(ValueError, match="is not an OpenCV dictionary"):
        aruco_dictionary(tmp_path / "camera.yml")


def test_bad_settings_are_refused_naming_them():
    cases = [
        ({"refinement": "sharp"}, "unknown corner refinement 'sharp'"),
        ({"parameters": {"adaptiveThreshWinSize": 5}}, "unknown detector parameter 'adaptiveThreshWinSize'"),
        ({"parameters": {"adaptiveThreshWinSizeMin": 5.5}}, "adaptiveThreshWinSizeMin must be int"),
        ({"parameters": {"detectInvertedMarker": 1}}, "detectInvertedMarker must be bool"),
        ({"parameters": {"cornerRefinementMethod": 1}}, "refinement="),
        ({"parameters": {"adaptiveThreshWinSizeMin": 2}}, "OpenCV rejects"),
        ({"marker_length": -0.1}, "marker_length must be"),
        ({"lengths": {3: 0.0}}, r"lengths\[3\] must be"),
        ({"lengths": {50: 0.1}}, "marker id 50 is not in the dictionary"),
    ]
    for settings, message in cases:
        with pytest.raises(ValueError, match=message):
            MarkerDetector("DICT_4X4_50", **settings)


def test_parameter_overrides_take_effect():
    dictionary = aruco_dictionary("DICT_4X4_50")
    inverted = 255 - marker_image(dictionary, 8)
    assert len(MarkerDetector(dictionary).detect(inverted)) == 0
    assert list(MarkerDetector(dictionary, parameters={"detectInvertedMarker": True}).detect(inverted).ids) == [8]


def test_lines_refinement_takes_the_calibration():
    scene = make_scene("markers")
    image, camera = scene.render(120).images["cam0"], scene.cameras[0]
    detector = MarkerDetector("DICT_4X4_50")
    plain, with_lens = detector.detect(image), detector.detect(image, camera.K, np.zeros(5))
    assert len(plain) > 0 and np.array_equal(plain.corners, with_lens.corners)
    bent = detector.detect(image, camera.K, np.array([0.2, 0.0, 0.0, 0.0, 0.0]))
    assert np.array_equal(bent.ids, plain.ids) and 0 < np.abs(bent.corners - plain.corners).max() < 0.5
