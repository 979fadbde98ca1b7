"""The stereo IR tracker: rigid bodies of spheres seen by a calibrated rig of N >= 2 cameras.

``correspondence`` turns the blobs of every camera into 3D points in the rig frame, ``rigid`` finds bodies
among them and fits ``T_world_body`` (4, 4), ``tracking`` follows each body from instant to instant,
``labelled`` labels the blobs by the bodies' predicted spheres and fits them without a search,
``centroid_noise`` estimates the blobs' noise, ``definition`` and ``file`` make and keep bodies, and
``node`` is the rigid bodies node."""

from __future__ import annotations

from services.estimation.bodies.centroid_noise import CentroidNoise
from services.estimation.bodies.correspondence import (
    CorrespondenceOptions,
    RigGeometry,
    rig_geometry,
    triangulate_blobs,
)
from services.estimation.bodies.definition import body_frame
from services.estimation.bodies.file import BodiesFileError, check_bodies, load_bodies, parse_bodies, save_bodies
from services.estimation.bodies.labelled import track_blobs
from services.estimation.bodies.rigid import BodyMatch, Matching, MatchOptions, match_bodies
from services.estimation.bodies.tracking import BodyTracker, TrackingOptions, match_with_prediction

__all__ = [
    "BodiesFileError",
    "BodyMatch",
    "BodyTracker",
    "CentroidNoise",
    "CorrespondenceOptions",
    "MatchOptions",
    "Matching",
    "RigGeometry",
    "TrackingOptions",
    "body_frame",
    "check_bodies",
    "load_bodies",
    "match_bodies",
    "match_with_prediction",
    "parse_bodies",
    "rig_geometry",
    "save_bodies",
    "track_blobs",
    "triangulate_blobs",
]
