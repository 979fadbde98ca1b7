"""The stereo tracker's steps run in-process on the ``ir_rig`` scene's rendered frames, scored against its truth.

``rendered_blobs`` renders frames and finds their blobs as a ``blobs`` node does (its default settings);
``track`` takes them through what the ``rigid_bodies`` node does per joined set (``node.BodiesPerSet``: the
unflagged blobs put in correspondence and triangulated, the bodies found and fitted, followed from frame
to frame with ``predict``, stamped with the scene's time; the covariance turned into the published
``Pose``'s) with any cameras, so one set of blobs can be tracked with the true rig and with a
calibrated one. Each ``Tracked`` pose is set beside the scene's truth of its frame.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from protocol.detections import Blobs
from protocol.message import Header
from services.detection.blobs.node import Params as BlobsParams
from services.detection.blobs.node import as_message, detector
from services.estimation.bodies.node import BodiesPerSet, Params, pixels
from services.geometry.absolute_orientation import child_frame_covariance
from services.geometry.camera import CameraModel
from services.geometry.rotation import rotation_angle, rotvec_from_matrix
from services.synthetic.ir_rig import IrRigScene


@dataclass(frozen=True)
class Tracked:
    """One published tracking pose: frame ``index``, ``body``, ``T_est`` / ``T_true`` (4, 4) ``T_world_body``,
    ``covariance`` (6, 6) as ``Pose.covariance`` (tx, ty, tz, rx, ry, rz in the body frame, m and rad) and the
    ``spheres`` used."""

    index: int
    body: str
    T_est: np.ndarray
    T_true: np.ndarray
    covariance: np.ndarray
    spheres: int

    @property
    def position_mm(self) -> float:
        return 1000.0 * float(np.linalg.norm(self.T_est[:3, 3] - self.T_true[:3, 3]))

    @property
    def rotation_deg(self) -> float:
        return float(np.degrees(rotation_angle(self.T_est[:3, :3], self.T_true[:3, :3])))

    @property
    def error(self) -> np.ndarray:
        """(6,) the truth as a perturbation of the estimate, ``Pose.covariance``'s order and frame: the
        translation ``R_est^T (t_true - t_est)`` (m), then the rotation vector of ``R_est^T R_true`` (rad)."""
        R_est_t = self.T_est[:3, :3].T
        return np.concatenate([R_est_t @ (self.T_true[:3, 3] - self.T_est[:3, 3]),
                               rotvec_from_matrix(R_est_t @ self.T_true[:3, :3])])


def rendered_blobs(scene: IrRigScene, indices: Sequence[int]) -> list[list[Blobs]]:
    """``blobs[f][c]``: the message the ``blobs`` node (default settings) publishes for camera ``c``'s image of
    frame ``indices[f]``."""
    params = BlobsParams()
    detect = detector(params)
    frames = []
    for index in indices:
        images = scene.render(index).images
        frames.append([as_message(Header(stamp_ns=int(scene.time_s(index) * 1e9), frame_id=camera.name, seq=index),
                                  params.method, detect(images[camera.name])) for camera in scene.cameras])
    return frames


def track(scene: IrRigScene, indices: Sequence[int], blobs: Sequence[Sequence[Blobs]],
          cameras: Sequence[CameraModel] | None = None, params: Params | None = None,
          T_frame_world: np.ndarray | None = None) -> list[Tracked]:
    """Every tracking pose the ``rigid_bodies`` node publishes for the frames ``indices`` (blobs from
    ``rendered_blobs``), with ``cameras`` (default: the scene's true rig) and the node's ``params``.

    ``T_frame_world``: (4, 4) the scene's world in the frame ``cameras`` are placed in (a calibrated rig's),
    which the truth is expressed in (default: identity, the scene's own rig)."""
    cameras = list(scene.cameras if cameras is None else cameras)
    params = params or Params(cameras=tuple(c.name for c in cameras))
    per_set = BodiesPerSet(scene.bodies, params)
    out = []
    for index, frame in zip(indices, blobs, strict=True):
        found, _ = per_set(round(scene.time_s(index) * 1e9), cameras, [pixels(b, params.flagged) for b in frame])
        truth = {name: T_world_body if T_frame_world is None else T_frame_world @ T_world_body
                 for name, T_world_body in scene.body_poses(index).items()}
        for name, match in found.matching.bodies.items():
            fit = match.fit
            assert fit.covariance is not None
            out.append(Tracked(index, name, fit.T_world_body, truth[name],
                               child_frame_covariance(fit.covariance, fit.T_world_body), match.spheres_used))
    return out


def whitened_rms(tracked: Sequence[Tracked]) -> np.ndarray:
    """(3,) root mean square of the position errors whitened by their published covariance, along each
    covariance's principal axes from the largest to the smallest: 1 where the covariance is honest."""
    rows = []
    for t in tracked:
        values, vectors = np.linalg.eigh(t.covariance[:3, :3])
        rows.append((vectors.T @ t.error[:3] / np.sqrt(values))[::-1])
    return np.sqrt(np.mean(np.square(rows), axis=0))


def mean_mahalanobis(tracked: Sequence[Tracked]) -> float:
    """Mean squared Mahalanobis distance of the position errors under their published covariance (3 if honest)."""
    return float(np.mean([t.error[:3] @ np.linalg.solve(t.covariance[:3, :3], t.error[:3]) for t in tracked]))


def summary(tracked: Sequence[Tracked]) -> dict[str, float | int]:
    """Count, position error median / p90 / max (mm) and rotation error median / p90 (deg)."""
    position = [t.position_mm for t in tracked]
    rotation = [t.rotation_deg for t in tracked]
    return {"poses": len(tracked), "position_mm_median": float(np.median(position)),
            "position_mm_p90": float(np.percentile(position, 90)), "position_mm_max": float(np.max(position)),
            "rotation_deg_median": float(np.median(rotation)),
            "rotation_deg_p90": float(np.percentile(rotation, 90))}
