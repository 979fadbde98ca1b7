"""What a marker tracker of one camera sets up once and keeps from frame to frame.

Shared by the marker pose node (``services.estimation.markers.node``) and the offline API
(``services.estimation.markers.offline``), so both detect with the same detector and report the same
targets as lost:

* ``marker_detector``: the detector detector settings describe, completed by the board's
  dictionary (when the settings name none) and its markers' side lengths;
* ``TargetTracks``: the targets posed in the previous frame, to tell which ones a frame lost
  (a target tracked in the previous frame and not in this one gets one ``lost`` pose).
"""

from __future__ import annotations

from collections.abc import Iterable

from services.detection.markers.detector import MarkerDetector
from services.detection.markers.settings import DetectorSettings
from services.estimation.markers.map import MarkerMap


def marker_detector(settings: DetectorSettings, board: MarkerMap | None) -> MarkerDetector:
    """The detector ``settings`` describe; with a ``board``, its dictionary stands in for the default one and its
    markers' side lengths are known (lengths in ``settings`` win). ValueError names a bad setting."""
    if board is None:
        return settings.detector()
    lengths = {marker_id: marker.length for marker_id, marker in board.markers.items()}
    return settings.detector(board.dictionary, lengths)


class TargetTracks:
    """The targets (``marker/<id>``, a board's name) that had a pose in the previous frame."""

    def __init__(self) -> None:
        self._tracked: set[str] = set()

    def update(self, tracked: Iterable[str]) -> list[str]:
        """Record this frame's ``tracked`` targets; return, sorted, those of the previous frame it lost."""
        now = set(tracked)
        lost = sorted(self._tracked - now)
        self._tracked = now
        return lost
