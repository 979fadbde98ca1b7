"""The local map cleaner: removes recent map points that failed their probation.

A point made within the last ``PROBATION`` keyframes fails when it was found in under
``cull_found_ratio`` of the tracked frames it was visible in, or when, two keyframes or more after its
making, fewer than ``cull_min_observations`` keyframes observe it (``SlamSettings``; ORB-SLAM's
recent map point culling). Older points are past culling.
"""

from __future__ import annotations

from services.slam.map.database import MapDatabase
from services.slam.map.map_point import MapPoint
from services.slam.settings import SlamSettings

__all__ = ["PROBATION", "LocalMapCleaner"]

PROBATION = 3
"""Keyframes after its making during which a point may be culled."""


class LocalMapCleaner:
    """Culls the failed recent points of ``database`` by ``settings``' policy."""

    def __init__(self, database: MapDatabase, settings: SlamSettings):
        self.database = database
        self.min_found_ratio = settings.cull_found_ratio
        self.min_observations = settings.cull_min_observations

    def failed(self, point: MapPoint, newest_keyframe: int) -> bool:
        """Whether ``point`` fails the policy of the module docstring once keyframe ``newest_keyframe`` exists."""
        return newest_keyframe - point.first_keyframe <= PROBATION and (
            point.found < self.min_found_ratio * point.visible
            or (newest_keyframe - point.first_keyframe >= 2 and len(point.observations) < self.min_observations))

    def cull_points(self, newest_keyframe: int) -> int:
        """Remove the points that fail once keyframe ``newest_keyframe`` exists; how many were removed.
        The points are judged outside the lock (their counters read as they are then) and judged again
        under it when removed."""
        database = self.database
        with database.lock:
            points = list(database.points.values())
        doomed = [p for p in points if self.failed(p, newest_keyframe)]
        with database.lock:
            removed = [p.id for p in doomed if database.points.get(p.id) is p and self.failed(p, newest_keyframe)]
            for point_id in removed:
                database.remove_point(point_id)
            return len(removed)
