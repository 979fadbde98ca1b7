"""Square fiducial markers (ArUco, AprilTag): found in one image, their corners refined, sheets printed.

``detector`` wraps ``cv2.aruco.ArucoDetector``, ``corner_lines`` refines corners by fitted sides,
``settings`` is the detector's options as nodes take them, ``sheet`` lays markers out at true scale, and
``node`` is the markers node."""

from __future__ import annotations

from services.detection.markers.corner_lines import refine_corners
from services.detection.markers.detector import MarkerDetector, MarkerFound, aruco_dictionary
from services.detection.markers.settings import DetectorSettings
from services.detection.markers.sheet import Sheet, charuco_sheet, grid_sheet, marker_sheet, write_pdf, write_png

__all__ = [
    "DetectorSettings",
    "MarkerDetector",
    "MarkerFound",
    "Sheet",
    "aruco_dictionary",
    "charuco_sheet",
    "grid_sheet",
    "marker_sheet",
    "refine_corners",
    "write_pdf",
    "write_png",
]
