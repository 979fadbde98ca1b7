"""Where the viewer puts things in a Rerun recording: entity paths and timelines.

Entity paths follow the frame ids, so the scene graph is the frame graph.

A frame named ``F`` (a header's ``frame_id``, a pose's ``child_frame_id``) is the entity
``world/F``, except the world frame itself (``world``, or an empty frame id), which is the
entity ``world``. Cameras are frames too, named after the camera (the capture node stamps its
frames with the camera's name), and every Rerun transform maps a child entity into its parent
entity, exactly as ``T_parent_child`` maps child coordinates into the parent frame::

    world                                 ViewCoordinates of the world frame (static)
    world/<cam>                           Transform3D T_world_cam (CameraInfo.T_rig_camera; rig = world)
    world/<cam>/image                     Pinhole (K, resolution, RDF; no distortion) + Image or EncodedImage
    world/<cam>/image/markers             LineStrips2D: marker outlines (corners closed), ids as labels
    world/<cam>/image/{clean,flagged}_blobs  Points2D: a Blobs message's blobs without / with flags,
                                          radius = the blob's radius (px)
    world/<cam>/image/keypoints           Points2D: feature positions
    world/<cam>/overlay/image             Image: the marker node's AR overlay of <cam> (frame id <cam>/overlay)
    <F>/pose/<child>                      Transform3D T_F_child + TransformAxes3D (Pose, RigidBodies)
    <F>/truth/<child>                     the same for GroundTruth, beside the estimate
    <F>/trajectory/pose/<child>           LineStrips3D: the child's last positions in F
    <F>/trajectory/truth/<child>          the same for ground truth
    <F>/keyframes/<child>                 Arrows3D: the x, y, z axes (red, green, blue) of each keyframe of a
                                          SLAM map in F (Keyframes), the child its camera
    <F>/points                            Points3D of a PointCloud expressed in F
    <F>/points/{labelled,unlabelled}      Points3D of a Points3D message: matched to a body (its name
                                          as label) or not, in two colours
    stats/rate_hz/<node>/<in|out>/<key>   Scalars: each stream's message rate
    stats/processing_ms/<node>/<p50|p99>  Scalars: processing time percentiles
    stats/dropped/<node>                  Scalars: frames dropped (latest-wins) so far
    stats/decode_errors/<node>            Scalars: payloads that failed to decode so far
    stats/stage_ms/<cam>/<stage>          Scalars: how long each stage of a frame of <cam> took (StageTimings)
    logs/<node>                           TextLog: the node's ErrorReports

``<F>`` is the entity of the message's parent frame, so a marker pose in camera ``cam0`` is
``world/cam0/pose/marker/7`` and a rigid body is ``world/pose/body/wand``. Pose and truth
entities sit under ``pose/`` and ``truth/`` rather than directly under ``<F>`` so that an
estimated camera pose (SLAM's ``T_world_cam0``) does not overwrite the calibrated camera
entity ``world/cam0``. An image, calibration or detection without a frame id belongs to the
camera ``camera``. An AR overlay is an Image whose frame id is ``<cam>/overlay``, so it is
the image of the camera ``<cam>/overlay``: an entity of its own under the camera's (Rerun
keeps one image per entity: under ``world/<cam>/image`` it would replace the camera's frames)
with a 2D view of its own. No CameraInfo names that camera, so it has no Pinhole and Rerun
leaves it out of the 3D view (the camera's own image is there already). Each
``/``-separated part of a name is escaped for Rerun.

Timelines: ``stamp`` (a timestamp: ``header.stamp_ns``, the capture time of the frame a message
derives from; the time it was made for NodeStats and ErrorReport) and ``seq`` (a sequence:
``header.seq``, the source frame's number; not set for NodeStats and ErrorReport, whose seq
counts their own messages). Rerun adds ``log_time`` (when the viewer logged the row).
"""

from __future__ import annotations

import rerun as rr

WORLD = "world"
UNNAMED_CAMERA = "camera"
STATS = "stats"
LOGS = "logs"
STAMP = "stamp"
SEQ = "seq"
ESTIMATE = "pose"
TRUTH = "truth"
RATE_HZ = "rate_hz"
PROCESSING_MS = "processing_ms"
LATENCY_MS = "latency_ms"
DROPPED = "dropped"
DECODE_ERRORS = "decode_errors"
STAGE_MS = "stage_ms"
CLEAN_BLOBS = "clean_blobs"
FLAGGED_BLOBS = "flagged_blobs"
LABELLED = "labelled"
UNLABELLED = "unlabelled"


def _escaped(name: str) -> str:
    return "/".join(rr.escape_entity_path_part(part) for part in name.split("/") if part)


def frame(name: str) -> str:
    """The entity of frame ``name`` (``world`` for the world frame or an empty name)."""
    if name in ("", WORLD):
        return WORLD
    return f"{WORLD}/{_escaped(name)}"


def camera(frame_id: str) -> str:
    """The name of the camera whose frame is ``frame_id``."""
    return frame_id or UNNAMED_CAMERA


def image(camera: str) -> str:
    """The camera's pinhole and image entity (its 2D space)."""
    return f"{frame(camera)}/image"


def detections(camera: str, kind: str) -> str:
    """An overlay in the camera's image: ``kind`` is ``markers``, ``keypoints``, ``CLEAN_BLOBS`` or
    ``FLAGGED_BLOBS``."""
    return f"{image(camera)}/{kind}"


def pose(parent_entity: str, child: str, source: str) -> str:
    """Where ``T_parent_child`` is logged; ``source`` is ``ESTIMATE`` or ``TRUTH``."""
    return f"{parent_entity}/{source}/{_escaped(child)}"


def trajectory(parent_entity: str, child: str, source: str) -> str:
    """The line of the child's past positions, in the parent frame."""
    return f"{parent_entity}/trajectory/{source}/{_escaped(child)}"


def keyframes(parent_entity: str, child: str) -> str:
    """The keyframes of a map in the parent frame, ``child`` the camera they were taken by."""
    return f"{parent_entity}/keyframes/{_escaped(child)}"


def points(frame_entity: str) -> str:
    return f"{frame_entity}/points"


def stats(metric: str, *parts: str) -> str:
    """A node statistic: ``stats/<metric>`` (every node's series) or ``stats/<metric>/<node>/...``."""
    return "/".join([STATS, metric, *(_escaped(p) for p in parts)])


def log(node: str) -> str:
    return f"{LOGS}/{_escaped(node)}"
