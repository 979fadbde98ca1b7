"""Square fiducial markers (ArUco, AprilTag) found in one image by ``cv2.aruco.ArucoDetector``.

Dictionaries are named as OpenCV names them (``DICT_4X4_50`` ... ``DICT_ARUCO_ORIGINAL``,
``DICT_APRILTAG_16h5/25h9/36h10/36h11``, ``DICT_ARUCO_MIP_36h12``) or given as the path of a
custom dictionary YAML as OpenCV writes it (``Dictionary.writeDictionary``: ``nmarkers``,
``markersize``, optional ``maxCorrectionBits``, ``marker_0`` ... as bit strings, row-major).

Corners are pixels of the input image (centre of the top-left pixel at (0, 0)), in OpenCV's
order: the marker's top-left, top-right, bottom-right, bottom-left corner as printed, which
is clockwise in the image when the marker faces the camera.

Quality is OpenCV's marker confidence (``ArucoDetector.detectMarkersWithConfidence``). The
detector warps the marker's quad to a canonical image of ``c = markerSize + 2 * markerBorderBits``
cells per side (``perspectiveRemovePixelPerCell`` px each, nearest neighbour), binarises it
with Otsu's threshold and measures each cell's white fraction ``r`` over the cell less a
margin of ``perspectiveRemoveIgnoredMarginPerCell`` of its side (for an inverted marker, ``1 - r``).
With ``b`` the bit (1 = white) the identified id and rotation demand in each inner cell::

    quality = clip(1 - (sum_border r + sum_inner |b - r|) / c**2, 0, 1)

so 1 means every sampled pixel has the colour the code demands, and each whole cell seen
with the wrong colour costs ``1 / c**2`` (1/36 for 4x4 markers, 1/64 for 6x6, one-bit border).
It drops when cells are sampled with the wrong colour: noise, glare, partial occlusion,
strong blur, bits the dictionary had to correct (``errorCorrectionRate``).
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Final

import cv2
import numpy as np

from services.detection.markers.corner_lines import refine_corners

DICTIONARY_NAMES: tuple[str, ...] = tuple(sorted(name for name in dir(cv2.aruco) if name.startswith("DICT_")))
"""Every predefined cv2.aruco dictionary name (AprilTag and MIP names in both spellings OpenCV has)."""

REFINEMENTS: dict[str, int] = {
    "lines": cv2.aruco.CORNER_REFINE_SUBPIX,
    "none": cv2.aruco.CORNER_REFINE_NONE,
    "subpix": cv2.aruco.CORNER_REFINE_SUBPIX,
    "contour": cv2.aruco.CORNER_REFINE_CONTOUR,
    "apriltag": cv2.aruco.CORNER_REFINE_APRILTAG,
}
"""Corner refinement names -> the cv2.aruco.CORNER_REFINE_* the detector runs (``subpix``: cornerSubPix
on the grey image; ``contour``: lines fitted to the marker's contour; ``apriltag``: AprilTag's quad
detection and fit; ``lines`` (default): ``subpix``, then lines fitted to subpixel edge points of each
side, intersected (``services.detection.markers.corner_lines``), which removes the inward pull cornerSubPix
has on blurred corners)."""
DEFAULT_REFINEMENT: Final = "lines"
SEARCH_CELLS = 0.4
"""``lines``: how far from each side its edge is looked for, in marker cells (the dark border is one
cell wide), clipped to ``SEARCH_PX``."""
SEARCH_PX = (0.75, 3.0)
LEVEL_CELLS = 0.5
"""``lines``: how far from each side the black and white levels are read, in marker cells: the middle of
the black border inside, as far into the white margin outside; at least the search distance, at most
``LEVEL_MAX_PX``."""
LEVEL_MAX_PX = 8.0

_DICTIONARY_SUFFIXES = (".yml", ".yaml", ".json", ".xml")
_PROBE_IMAGE = np.zeros((64, 64), np.uint8)
_PROBE_K = np.array([[300.0, 0.0, 100.0], [0.0, 300.0, 100.0], [0.0, 0.0, 1.0]])
_PROBE_DIST = np.array([0.05, -0.02, 0.0, 0.0, 0.0])
"""A camera for the probe below: the detector refines its marker once when built, with and without one."""


def _marker_probe(dictionary: cv2.aruco.Dictionary) -> np.ndarray:
    """(200, 200) uint8: the dictionary's marker 0, 96 px wide with a white margin, slightly blurred."""
    image = np.full((200, 200), 255, np.uint8)
    image[52:148, 52:148] = cv2.aruco.generateImageMarker(dictionary, 0, 96)
    return cv2.GaussianBlur(image, (5, 5), 1.0)


def aruco_dictionary(name_or_path: str | Path) -> cv2.aruco.Dictionary:
    """The cv2.aruco dictionary ``name_or_path`` names: a predefined name or a custom dictionary file.

    A string counts as a path when it is a ``Path``, contains a path separator, ends in
    .yml/.yaml/.json/.xml or names an existing file. Raises ValueError listing the valid
    names for an unknown name, and naming the file when it is missing or not a dictionary.
    """
    if isinstance(name_or_path, str) and name_or_path in DICTIONARY_NAMES:
        return cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name_or_path))
    if not _looks_like_path(name_or_path):
        raise ValueError(f"unknown marker dictionary {name_or_path!r}: use one of {', '.join(DICTIONARY_NAMES)} "
                         "or the path of a dictionary YAML file")
    return _read_dictionary(Path(name_or_path))


def _looks_like_path(value: object) -> bool:
    if isinstance(value, Path):
        return True
    if not isinstance(value, str) or not value:
        return False
    return "/" in value or value.lower().endswith(_DICTIONARY_SUFFIXES) or Path(value).is_file()


def _read_dictionary(path: Path) -> cv2.aruco.Dictionary:
    if not path.is_file():
        raise ValueError(f"marker dictionary file {path} does not exist")
    storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    try:
        dictionary = cv2.aruco.Dictionary()
        ok = storage.isOpened() and dictionary.readDictionary(storage.root())
    except cv2.error as exc:
        raise ValueError(f"marker dictionary file {path} cannot be read: {exc.err}") from exc
    finally:
        storage.release()
    if not ok or dictionary.markerSize <= 0 or dictionary.bytesList is None or len(dictionary.bytesList) == 0:
        raise ValueError(f"marker dictionary file {path} is not an OpenCV dictionary "
                         "(needs nmarkers, markersize and marker_0 ... as bit strings)")
    return dictionary


def to_grey(image: np.ndarray) -> np.ndarray:
    """(H, W) uint8 grey image of a mono8 (H, W), bgr8 (H, W, 3), bgra8 (H, W, 4) or mono16 (H, W) uint16 image.

    mono16 is stretched linearly so its darkest pixel becomes 0 and its brightest 255
    (sensors fill 10 to 16 bits of it; the detector thresholds locally, so only contrast matters).
    """
    image = np.asarray(image)
    channels = 1 if image.ndim == 2 else (image.shape[2] if image.ndim == 3 else 0)
    if image.dtype == np.uint8 and channels == 1:
        return image
    if image.dtype == np.uint8 and channels == 3:
        return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if image.dtype == np.uint8 and channels == 4:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2GRAY)
    if image.dtype == np.uint16 and channels == 1:
        return cv2.normalize(image, None, 0, 255, cv2.NORM_MINMAX, dtype=cv2.CV_8U)  # type: ignore[call-overload]
    raise ValueError(f"images must be mono8, bgr8, bgra8 or mono16; got {image.dtype} of shape {image.shape}")


@dataclass(frozen=True)
class MarkerFound:
    """Markers found in one image, row ``i`` of every array describing marker ``i``, sorted by id.

    ``ids``: (N,) int32; ``corners``: (N, 4, 2) float32 px, TL, TR, BR, BL of each marker as
    printed; ``quality``: (N,) float32 in [0, 1], higher is better (see the module docstring);
    ``side_m``: (N,) float32, each marker's configured side length in metres, 0 when unknown.
    """

    ids: np.ndarray
    corners: np.ndarray
    quality: np.ndarray
    side_m: np.ndarray

    def __len__(self) -> int:
        return len(self.ids)


class MarkerDetector:
    """Finds the markers of one dictionary in images (cv2.aruco.ArucoDetector).

    ``dictionary``: a predefined name, a dictionary file path or a cv2.aruco.Dictionary.
    ``marker_length``: side of every marker's black square in metres (0 = unknown);
    ``lengths``: per-id overrides of it. ``refinement``: a key of ``REFINEMENTS`` (default ``lines``:
    OpenCV's ``subpix`` corners moved to the intersections of lines fitted to each side's edge,
    searched ``SEARCH_CELLS`` of a cell either side, the black and white levels read ``LEVEL_CELLS`` of
    a cell either side (see ``corner_lines``); the lines are fitted in the distorted image unless
    ``detect`` is given the calibration).
    ``parameters``: cv2.aruco.DetectorParameters fields to override, by their OpenCV names
    (e.g. ``{"adaptiveThreshWinSizeMax": 33, "detectInvertedMarker": True}``); the corner
    refinement method is set through ``refinement`` only. Raises ValueError naming whatever
    is wrong: an unknown dictionary, refinement or field, a value of the wrong type, or
    settings OpenCV rejects.
    """

    def __init__(self, dictionary: str | Path | cv2.aruco.Dictionary, *, marker_length: float = 0.0,
                 lengths: Mapping[int, float] | None = None, refinement: str = DEFAULT_REFINEMENT,
                 parameters: Mapping[str, object] | None = None):
        self.dictionary = dictionary if isinstance(dictionary, cv2.aruco.Dictionary) else aruco_dictionary(dictionary)
        size = len(self.dictionary.bytesList)
        self.marker_length = _length("marker_length", marker_length, allow_zero=True)
        self.lengths = {_marker_id(i, size): _length(f"lengths[{i}]", v, allow_zero=False)
                        for i, v in (lengths or {}).items()}
        if refinement not in REFINEMENTS:
            raise ValueError(f"unknown corner refinement {refinement!r}: use one of {', '.join(REFINEMENTS)}")
        self.refinement = refinement
        params = detector_parameters(parameters or {})
        params.cornerRefinementMethod = REFINEMENTS[refinement]
        self._detector = cv2.aruco.ArucoDetector(self.dictionary, params)
        try:
            self._detector.detectMarkersWithConfidence(_PROBE_IMAGE)
        except cv2.error as exc:
            raise ValueError(f"OpenCV rejects these detector parameters: {exc.err}") from exc
        if refinement == "lines":  # the first refinements' one-off set-up is paid here, not on a frame
            probe = _marker_probe(self.dictionary)
            self.detect(probe)
            self.detect(probe, _PROBE_K, _PROBE_DIST)

    def side_lengths(self, ids: np.ndarray) -> np.ndarray:
        """(N,) float32 side lengths in metres of markers ``ids`` ((N,) ints); 0 when unknown."""
        return np.array([self.lengths.get(int(i), self.marker_length) for i in ids], dtype=np.float32)

    def reach_px(self, corners: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """For quads ``corners`` (N, 4, 2) px, what ``lines`` needs: how far from each side its edge is
        looked for and how far the black and white levels are read, (N,) px each."""
        side = np.linalg.norm(corners - np.roll(corners, -1, axis=1), axis=2).mean(axis=1)
        cells = self.dictionary.markerSize + 2 * self._detector.getDetectorParameters().markerBorderBits
        search = np.clip(SEARCH_CELLS * side / cells, *SEARCH_PX)
        return search, np.clip(LEVEL_CELLS * side / cells, search, LEVEL_MAX_PX)

    def detect(self, image: np.ndarray, K: np.ndarray | None = None, dist: np.ndarray | None = None) -> MarkerFound:
        """The markers in ``image`` (mono8 / bgr8 / bgra8 / mono16 array, see ``to_grey``), sorted by id.

        Several markers with one id come in the order of their first corner (x, then y). ``K``
        (3, 3) and ``dist`` (OpenCV distortion coefficients), when known, let the ``lines``
        refinement fit the sides in undistorted pixels (corners stay distorted pixels).
        """
        grey = to_grey(image)
        found, found_ids, confidence, _ = self._detector.detectMarkersWithConfidence(grey)
        if found_ids is None or len(found_ids) == 0:
            return MarkerFound(np.zeros(0, np.int32), np.zeros((0, 4, 2), np.float32),
                               np.zeros(0, np.float32), np.zeros(0, np.float32))
        ids = np.asarray(found_ids, dtype=np.int32).reshape(-1)
        corners = np.asarray(found, dtype=np.float32).reshape(-1, 4, 2)
        if self.refinement == "lines":
            search, level = self.reach_px(corners)
            corners = refine_corners(grey, corners, search, K=K, dist=dist, level_px=level)
        quality = np.asarray(confidence, dtype=np.float32).reshape(-1)
        order = np.lexsort((corners[:, 0, 1], corners[:, 0, 0], ids))
        ids = ids[order]
        return MarkerFound(ids, corners[order], quality[order], self.side_lengths(ids))


def detector_parameters(overrides: Mapping[str, object]) -> cv2.aruco.DetectorParameters:
    """cv2.aruco.DetectorParameters with OpenCV's defaults and ``overrides`` (field name -> value) applied.

    Booleans must be bool, integers int, real numbers int or float. ValueError names an
    unknown field (listing the known ones) or a value of the wrong type.
    """
    params = cv2.aruco.DetectorParameters()
    fields = parameter_fields()
    for name, value in overrides.items():
        if name == "cornerRefinementMethod":
            raise ValueError(f"detector parameter {name}: set the corner refinement with refinement="
                             f"{'|'.join(REFINEMENTS)} instead")
        if name not in fields:
            raise ValueError(f"unknown detector parameter {name!r}: known are {', '.join(sorted(fields))}")
        kind = fields[name]
        valid = {bool: isinstance(value, bool),
                 int: isinstance(value, numbers.Integral) and not isinstance(value, bool),
                 float: isinstance(value, numbers.Real) and not isinstance(value, bool)
                 and math.isfinite(float(value))}[kind]
        if not valid:
            raise ValueError(f"detector parameter {name} must be {kind.__name__}, got {value!r}")
        setattr(params, name, kind(value))
    return params


def parameter_fields() -> dict[str, type]:
    """Settable cv2.aruco.DetectorParameters fields -> their Python type (bool, int or float)."""
    defaults = cv2.aruco.DetectorParameters()
    fields = {}
    for name in dir(defaults):
        value = getattr(defaults, name)
        if not name.startswith("_") and isinstance(value, bool | int | float):
            fields[name] = type(value)
    return fields


def _length(what: str, value: object, *, allow_zero: bool) -> float:
    if not (isinstance(value, numbers.Real) and not isinstance(value, bool) and math.isfinite(float(value))
            and (float(value) > 0 or (allow_zero and float(value) == 0))):
        bound = ">= 0" if allow_zero else "> 0"
        raise ValueError(f"{what} must be a finite length in metres {bound}, got {value!r}")
    return float(value)


def _marker_id(value: object, size: int) -> int:
    if not (isinstance(value, numbers.Integral) and not isinstance(value, bool) and 0 <= int(value) < size):
        raise ValueError(f"marker id {value!r} is not in the dictionary (ids 0 to {size - 1})")
    return int(value)
