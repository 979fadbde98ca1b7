"""SLAM map files: a map saved after a run, loaded by a later one to localise against it.

One ``.npz`` file (``numpy.savez_compressed``, no pickled objects) holds a JSON header and flat
arrays. The header (entry ``header``, UTF-8 bytes as uint8):

    {"format": "artrack-slam-map", "version": 1, "created": "<ISO 8601 UTC>",
     "camera": {"name": str, "width": int, "height": int, "K": 3x3 list, "dist": 5 list},
     "pyramid": {"levels": int, "scale_factor": float},
     "counts": {"keyframes": K, "keypoints": N, "points": P, "observations": M}}

Arrays (K keyframes holding N keypoints in all, P points, M observations):

* ``keyframe_ids`` (K,) int64, ``keyframe_stamps_ns`` (K,) int64, ``keyframe_poses`` (K, 4, 4)
  float64 ``T_camera_world``, ``keyframe_offsets`` (K + 1,) int64: keyframe ``k``'s keypoints are
  rows ``offsets[k]:offsets[k + 1]`` of
* ``keypoint_pixels`` (N, 2) float64 undistorted px, ``keypoint_levels`` (N,) int64,
  ``keypoint_angles`` (N,) float32 degrees, ``keypoint_descriptors`` (N, 32) uint8 ORB;
* ``point_ids`` (P,) int64, ``point_positions`` (P, 3) float64 world, ``point_visible`` and
  ``point_found`` (P,) int64 (the tracking counters);
* ``observation_points``, ``observation_keyframes``, ``observation_keypoints`` (M,) int64: point id,
  keyframe id, keypoint index within that keyframe; each point's in the order it gained them (its
  representative descriptor breaks ties by that order).

A point's representative descriptor, viewing direction and distance range are not stored: loading
recomputes them from the observations (``MapDatabase.update_point``), as the mapper does. Loading
renumbers keyframes and points in their saved order.

A file is refused with ``MapFileError`` (a ValueError), one line naming the file and what is
wrong: not a map file (truncated, damaged, garbage, another format; a recording or an image given by
mistake is named as such), another version, another
camera (image size, or ``K`` entries more than ``K_TOLERANCE_PX`` apart, or distortion more than
``DIST_TOLERANCE``), or arrays that do not agree with each other. A file that cannot be written
raises it too.
"""

from __future__ import annotations

import json
import os
import zipfile
import zlib
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from services.geometry.camera import CameraModel
from services.slam.features import FrameFeatures
from services.slam.map.database import MapDatabase

__all__ = ["FORMAT", "VERSION", "K_TOLERANCE_PX", "DIST_TOLERANCE", "MapFileError", "save_map", "load_map",
           "read_header"]

FORMAT = "artrack-slam-map"
VERSION = 1
K_TOLERANCE_PX = 0.5
"""Largest difference of focal lengths and principal point (px) between the file's camera and the one given."""
DIST_TOLERANCE = 1e-4
DESCRIPTOR_BYTES = 32


ZIP_SIGNATURE = b"PK\x03\x04"
"""How an .npz archive (a zip file) starts."""
OTHER_FILES = ((b"\x89MCAP", "an MCAP recording"), (b"\x89PNG", "a PNG image"), (b"\xff\xd8\xff", "a JPEG image"),
               (b"%PDF", "a PDF document"))
"""How files given by mistake for a map start, and what they are: (leading bytes, what to call it)."""


class MapFileError(ValueError):
    """A map file that cannot be used: the message names the file and why."""

    def __init__(self, path: str | os.PathLike[str], why: str):
        super().__init__(f"map file {os.fspath(path)}: {why}")


def _camera_header(camera: CameraModel) -> dict[str, Any]:
    return {"name": camera.name, "width": int(camera.width), "height": int(camera.height),
            "K": np.asarray(camera.K, np.float64).tolist(),
            "dist": np.asarray(camera.dist, np.float64).ravel().tolist()}


def save_map(slam_map: MapDatabase, camera: CameraModel, path: str | os.PathLike[str]) -> dict[str, Any]:
    """Write ``slam_map`` of ``camera`` to ``path`` (replaced atomically: written beside it, then
    renamed). Returns the header written; ``MapFileError`` when the file cannot be written."""
    with slam_map.lock:
        keyframes = [slam_map.keyframes[k] for k in sorted(slam_map.keyframes)]
        points = [slam_map.points[p] for p in sorted(slam_map.points)]
        sizes = [len(k.features) for k in keyframes]
        observations = np.array([(p.id, k, i) for p in points for k, i in p.observations.items()],
                                np.int64).reshape(-1, 3)
        arrays = {
            "keyframe_ids": np.array([k.id for k in keyframes], np.int64),
            "keyframe_stamps_ns": np.array([k.stamp_ns for k in keyframes], np.int64),
            "keyframe_poses": np.array([k.T_camera_world for k in keyframes], np.float64).reshape(-1, 4, 4),
            "keyframe_offsets": np.r_[0, np.cumsum(sizes)].astype(np.int64),
            "keypoint_pixels": _stack([k.features.pixels for k in keyframes], (0, 2), np.float64),
            "keypoint_levels": _stack([k.features.levels for k in keyframes], (0,), np.int64),
            "keypoint_angles": _stack([k.features.angles for k in keyframes], (0,), np.float32),
            "keypoint_descriptors": _stack([k.features.descriptors for k in keyframes], (0, DESCRIPTOR_BYTES),
                                           np.uint8),
            "point_ids": np.array([p.id for p in points], np.int64),
            "point_positions": np.array([p.position for p in points], np.float64).reshape(-1, 3),
            "point_visible": np.array([p.visible for p in points], np.int64),
            "point_found": np.array([p.found for p in points], np.int64),
            "observation_points": observations[:, 0].copy(),
            "observation_keyframes": observations[:, 1].copy(),
            "observation_keypoints": observations[:, 2].copy(),
        }
        header = {"format": FORMAT, "version": VERSION, "created": datetime.now(UTC).isoformat(timespec="seconds"),
                  "camera": _camera_header(camera),
                  "pyramid": {"levels": slam_map.levels, "scale_factor": slam_map.scale_factor},
                  "counts": {"keyframes": len(keyframes), "keypoints": int(sum(sizes)), "points": len(points),
                             "observations": len(observations)}}
    target = Path(path)
    partial = target.with_name(target.name + ".partial")
    try:
        with open(partial, "wb") as stream:
            np.savez_compressed(stream, header=np.frombuffer(json.dumps(header).encode(), np.uint8), **arrays)
        os.replace(partial, target)
    except OSError as error:
        partial.unlink(missing_ok=True)
        raise MapFileError(path, f"cannot be written ({error.strerror or error})") from None
    return header


def _stack(parts: list[np.ndarray], empty: tuple[int, ...], dtype: type) -> np.ndarray:
    return np.concatenate(parts).astype(dtype) if parts else np.zeros(empty, dtype)


def _open(path: str | os.PathLike[str]) -> dict[str, np.ndarray]:
    try:
        with open(path, "rb") as stream:
            start = stream.read(8)
    except FileNotFoundError:
        raise MapFileError(path, "no such file") from None
    except OSError as error:
        raise MapFileError(path, f"cannot be read ({error.strerror or error})") from None
    if not start.startswith(ZIP_SIGNATURE):
        what = next((name for signature, name in OTHER_FILES if start.startswith(signature)), None)
        raise MapFileError(path, f"not a map file: {what} (a map file is the .npz archive --save-map writes)"
                           if what else "not a readable map file (not an .npz archive, which --save-map writes)")
    try:
        with np.load(path, allow_pickle=False) as archive:
            return {name: archive[name] for name in archive.files}
    except FileNotFoundError:
        raise MapFileError(path, "no such file") from None
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error) as error:
        raise MapFileError(path, f"not a readable map file (truncated, damaged or not an .npz archive: "
                                 f"{error})") from None


def _header(path: str | os.PathLike[str], arrays: dict[str, np.ndarray]) -> dict[str, Any]:
    if "header" not in arrays:
        raise MapFileError(path, f"not a map file (no header; {FORMAT} expected)")
    try:
        header = json.loads(arrays["header"].tobytes().decode())
    except (UnicodeDecodeError, json.JSONDecodeError):
        raise MapFileError(path, "not a map file (its header is not JSON)") from None
    if not isinstance(header, dict) or header.get("format") != FORMAT:
        found = header.get("format") if isinstance(header, dict) else None
        raise MapFileError(path, f"not a map file (format {found!r}, {FORMAT!r} expected)")
    if header.get("version") != VERSION:
        raise MapFileError(path, f"format version {header.get('version')!r}, this program reads version {VERSION}")
    return header


def read_header(path: str | os.PathLike[str]) -> dict[str, Any]:
    """The checked header of the map file ``path`` (format and version); MapFileError otherwise."""
    return _header(path, _open(path))


def _check_camera(path: str | os.PathLike[str], header: dict[str, Any], camera: CameraModel) -> None:
    try:
        saved = header["camera"]
        size = (int(saved["width"]), int(saved["height"]))
        K = np.asarray(saved["K"], np.float64).reshape(3, 3)
        dist = np.asarray(saved["dist"], np.float64).ravel()
    except (KeyError, TypeError, ValueError):
        raise MapFileError(path, "its header has no usable camera") from None
    if size != (camera.width, camera.height):
        raise MapFileError(path, f"made for a {size[0]}x{size[1]} camera, this camera is "
                                 f"{camera.width}x{camera.height}")
    own = np.asarray(camera.K, np.float64)
    entries = {"fx": (0, 0), "fy": (1, 1), "cx": (0, 2), "cy": (1, 2)}
    differ = [f"{name} {K[i]:.2f} vs {own[i]:.2f}" for name, i in entries.items()
              if abs(K[i] - own[i]) > K_TOLERANCE_PX]
    if differ:
        raise MapFileError(path, f"made for another camera matrix ({', '.join(differ)} px; tolerance "
                                 f"{K_TOLERANCE_PX} px)")
    own_dist = np.asarray(camera.dist, np.float64).ravel()
    count = max(len(dist), len(own_dist))
    if np.max(np.abs(np.pad(dist, (0, count - len(dist))) - np.pad(own_dist, (0, count - len(own_dist))))) \
            > DIST_TOLERANCE:
        raise MapFileError(path, f"made for another lens distortion ({dist.tolist()} vs {own_dist.tolist()})")


def _checked_arrays(path: str | os.PathLike[str], header: dict[str, Any],
                    arrays: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The arrays, checked for presence, shapes, dtypes and agreement with the header's counts."""
    try:
        counts = {name: int(header["counts"][name]) for name in ("keyframes", "keypoints", "points", "observations")}
    except (KeyError, TypeError, ValueError):
        raise MapFileError(path, "its header has no usable counts") from None
    K, N, P, M = counts["keyframes"], counts["keypoints"], counts["points"], counts["observations"]
    expected = {
        "keyframe_ids": ((K,), np.integer), "keyframe_stamps_ns": ((K,), np.integer),
        "keyframe_poses": ((K, 4, 4), np.floating), "keyframe_offsets": ((K + 1,), np.integer),
        "keypoint_pixels": ((N, 2), np.floating), "keypoint_levels": ((N,), np.integer),
        "keypoint_angles": ((N,), np.floating), "keypoint_descriptors": ((N, DESCRIPTOR_BYTES), np.uint8),
        "point_ids": ((P,), np.integer), "point_positions": ((P, 3), np.floating),
        "point_visible": ((P,), np.integer), "point_found": ((P,), np.integer),
        "observation_points": ((M,), np.integer), "observation_keyframes": ((M,), np.integer),
        "observation_keypoints": ((M,), np.integer),
    }
    for name, (shape, kind) in expected.items():
        array = arrays.get(name)
        if array is None:
            raise MapFileError(path, f"array {name} is missing")
        if array.shape != shape or not np.issubdtype(array.dtype, kind):
            raise MapFileError(path, f"array {name} is {array.dtype} {array.shape}, {kind.__name__} {shape} expected")
    offsets = arrays["keyframe_offsets"]
    if offsets[0] != 0 or offsets[-1] != N or np.any(np.diff(offsets) < 0):
        raise MapFileError(path, "keyframe offsets do not cover the keypoints")
    if not (np.all(np.isfinite(arrays["keyframe_poses"])) and np.all(np.isfinite(arrays["point_positions"]))
            and np.all(np.isfinite(arrays["keypoint_pixels"]))):
        raise MapFileError(path, "poses, positions or pixels are not finite")
    rows = {int(k): r for r, k in enumerate(arrays["keyframe_ids"].tolist())}
    keyframe_rows = np.array([rows.get(int(k), -1) for k in arrays["observation_keyframes"].tolist()], np.int64)
    sizes = np.diff(offsets)
    if (len(rows) != K or len(np.unique(arrays["point_ids"])) != P or np.any(keyframe_rows < 0)
            or not np.all(np.isin(arrays["observation_points"], arrays["point_ids"]))
            or np.any(arrays["observation_keypoints"] < 0)
            or np.any(arrays["observation_keypoints"] >= sizes[np.maximum(keyframe_rows, 0)])):
        raise MapFileError(path, "observations refer to keyframes, points or keypoints it does not hold")
    arrays["observation_keyframe_rows"] = keyframe_rows
    return arrays


def load_map(path: str | os.PathLike[str], camera: CameraModel) -> MapDatabase:
    """The map saved in ``path`` for ``camera``; ``MapFileError`` (one line) when the file is not a
    map file of this version, was made for another camera, or is inconsistent."""
    arrays = _open(path)
    header = _header(path, arrays)
    _check_camera(path, header, camera)
    arrays = _checked_arrays(path, header, arrays)
    try:
        pyramid = header["pyramid"]
        slam_map = MapDatabase(float(pyramid["scale_factor"]), int(pyramid["levels"]))
    except (KeyError, TypeError, ValueError):
        raise MapFileError(path, "its header has no usable pyramid") from None
    offsets = arrays["keyframe_offsets"]
    keyframe_ids = []
    for row in range(len(arrays["keyframe_ids"])):
        rows = slice(int(offsets[row]), int(offsets[row + 1]))
        levels = arrays["keypoint_levels"][rows].astype(np.int64)
        features = FrameFeatures(pixels=arrays["keypoint_pixels"][rows].astype(np.float64), levels=levels,
                                 angles=arrays["keypoint_angles"][rows].astype(np.float32),
                                 descriptors=np.ascontiguousarray(arrays["keypoint_descriptors"][rows]),
                                 sigmas=np.power(slam_map.scale_factor, levels.astype(np.float64)))
        keyframe = slam_map.add_keyframe(int(arrays["keyframe_stamps_ns"][row]), arrays["keyframe_poses"][row],
                                         features, np.full(len(features), -1, np.int64))
        keyframe_ids.append(keyframe.id)
    order = np.argsort(arrays["observation_points"], kind="stable")
    points, starts = np.unique(arrays["observation_points"][order], return_index=True)
    groups = np.split(order, starts[1:]) if len(order) else []
    observations = dict(zip(points.tolist(), groups, strict=True))
    for row, point_id in enumerate(arrays["point_ids"].tolist()):
        seen = observations.get(point_id)
        if seen is None:
            continue
        new_id = slam_map.add_point(arrays["point_positions"][row], {
            keyframe_ids[int(arrays["observation_keyframe_rows"][m])]: int(arrays["observation_keypoints"][m])
            for m in seen})
        point = slam_map.points[new_id]
        point.visible, point.found = int(arrays["point_visible"][row]), int(arrays["point_found"][row])
    return slam_map
