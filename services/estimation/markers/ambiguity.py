"""The planar ambiguity: which of a target's two candidate poses to trust, from its track.

A planar target admits two poses under perspective (``services.geometry.planar_pnp``). When the
second candidate's reprojection RMS is below ``ratio`` times the best's, the view is ambiguous:
noise alone may decide which candidate scores lower. The tracker then prefers the candidate whose
rotation is closest to the target's last pose, if that pose is recent (at most ``prior_max_age``
frames old) and anchored; otherwise the lower error wins.

A pose is anchored when it was unambiguous, or was itself chosen by an anchored track; a pose
picked by its lower error in an ambiguous view is a guess and anchors nothing, so a guess never
propagates from frame to frame (the idea of ArUco's MarkerPoseTracker). A wider ``ratio`` hands
more views to the track, which is itself noisy; the default 2 is the value that gave the smallest
error tail on the noisy views of the accuracy data set (its share of ambiguous views: docs/benchmarks.md).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from services.geometry.planar_pnp import Candidate
from services.geometry.rotation import rotation_angle


@dataclass(frozen=True)
class Track:
    """A target's last pose: the tracker's frame number, ``T`` (4, 4) ``T_camera_target``, and whether it
    is anchored (unambiguous, or chosen by an anchored track)."""

    frame: int
    T: np.ndarray
    anchored: bool


class AmbiguityTracker:
    """Each target's last pose, by target name, and the choice between two candidates it decides.

    ``next_frame`` starts a frame (the age of every track grows by one); ``choose`` picks a target's
    candidate; ``record`` keeps the pose the target finally got.
    """

    def __init__(self, ratio: float = 2.0, prior_max_age: int = 5):
        if not (ratio >= 1 and prior_max_age >= 0):
            raise ValueError(f"need ambiguity ratio >= 1 and prior_max_age >= 0, got {ratio} and {prior_max_age}")
        self.ratio = ratio
        self.prior_max_age = prior_max_age
        self.frame = 0
        self._tracks: dict[str, Track] = {}

    def next_frame(self) -> None:
        """Start the next frame."""
        self.frame += 1

    def reset(self) -> None:
        """Forget every target's track (the frame count goes on)."""
        self._tracks.clear()

    def track(self, target: str) -> Track | None:
        """The target's last recorded pose, if any."""
        return self._tracks.get(target)

    def is_ambiguous(self, candidates: Sequence[Candidate]) -> bool:
        """Whether two candidates (lowest RMS first) explain the points almost equally well."""
        return len(candidates) == 2 and candidates[1].rms_px < self.ratio * candidates[0].rms_px

    def choose(self, target: str, candidates: Sequence[Candidate], ambiguous: bool) -> tuple[Candidate, bool]:
        """The candidate closest in rotation to the target's anchored track when the view is ambiguous
        and the track at most ``prior_max_age`` frames old, else the lowest RMS; and whether the choice
        is anchored."""
        track = self._tracks.get(target)
        if ambiguous and len(candidates) > 1 and track is not None and track.anchored \
                and self.frame - track.frame <= self.prior_max_age:
            return min(candidates, key=lambda c: rotation_angle(c.T[:3, :3], track.T[:3, :3])), True
        return min(candidates, key=lambda c: c.rms_px), not ambiguous

    def record(self, target: str, T: np.ndarray, anchored: bool) -> None:
        """Keep ``T`` (4, 4) as the target's pose in this frame."""
        self._tracks[target] = Track(self.frame, T, anchored)
