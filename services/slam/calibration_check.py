"""Whether the camera matrix fits the images, from the map: its keyframes and points bundle adjusted twice
by Ceres through pycolmap, the focal lengths and principal point fixed, then free.

A wrong focal length or principal point leaves tracking going: the map bends to fit it, and each
frame's reprojection error stays within what right calibrations give on other cameras. Freed, the
focal lengths and principal point of a wrong matrix move and the reprojection error falls; those of a
right one move only where the motion leaves them unobservable (forward driving, a principal point
along the direction the camera does not sweep), and there the error does not fall. The check calls
the matrix suspect when both happen: a focal length moves by ``MIN_FOCAL_CHANGE`` or more, or the
principal point by ``MIN_PRINCIPAL_SHIFT`` of the image's width or more, and the median reprojection
error falls by ``MIN_ERROR_DROP`` or more.

Frames: keyframe poses ``T_camera_world`` and points in the map's world; pixels undistorted.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pycolmap

from services.slam.map.database import MapDatabase
from services.slam.optimisation import reprojection_errors

__all__ = ["CHECK_KEYFRAMES", "FocalCheck", "check_focal"]

CHECK_KEYFRAMES = 5
"""The local mapper checks the camera matrix against the map once, after mapping a keyframe of a map that holds
this many keyframes (``mapping.LocalMapper``, in the mapping process too): never on the frames' path."""
MIN_FOCAL_CHANGE = 0.10
MIN_PRINCIPAL_SHIFT = 0.05
MIN_ERROR_DROP = 0.03
HUBER_PX = 2.0


@dataclass(frozen=True)
class FocalCheck:
    """The given focal lengths ``fx``, ``fy`` (px), those the map's images ask for when free, and the
    median reprojection errors (px) of the map's observations after each adjustment."""

    fx: float
    fy: float
    free_fx: float
    free_fy: float
    error_fixed_px: float
    error_free_px: float
    principal_shift: float = 0.0
    """How far the principal point moved when free, a fraction of the image's width."""
    took_ms: float = 0.0
    """How long the check took where it ran (the mapper's thread or process), ms."""

    @property
    def suspect(self) -> bool:
        focal = max(abs(self.free_fx / self.fx - 1), abs(self.free_fy / self.fy - 1)) >= MIN_FOCAL_CHANGE
        moved = focal or self.principal_shift >= MIN_PRINCIPAL_SHIFT
        return moved and self.error_free_px <= (1 - MIN_ERROR_DROP) * self.error_fixed_px

    def line(self) -> str:
        return (f"focal lengths {self.fx:.1f}, {self.fy:.1f} px given, {self.free_fx:.1f}, {self.free_fy:.1f} px "
                f"when free, the principal point moved {100 * self.principal_shift:.1f} % of the image's width "
                f"(median reprojection error of the map {self.error_fixed_px:.3f} -> {self.error_free_px:.3f} px)")


def check_focal(slam_map: MapDatabase, K: np.ndarray, size: tuple[int, int]) -> FocalCheck | None:
    """The check of the module docstring on a snapshot of ``slam_map`` (taken under its lock) for the
    (3, 3) ``K`` of a camera of ``size`` (width, height) px; None with fewer than three keyframes."""
    with slam_map.lock:
        keyframes = sorted(slam_map.keyframes)
        if len(keyframes) < 3:
            return None
        poses = np.array([slam_map.keyframes[k].T_camera_world for k in keyframes])
        pixels = [slam_map.keyframes[k].features.pixels.copy() for k in keyframes]
        row = {k: n for n, k in enumerate(keyframes)}
        tracks = [(p.position.copy(), [(row[k], i) for k, i in p.observations.items()])
                  for p in slam_map.points.values() if len(p.observations) >= 2]
    fixed = _adjusted(K, size, poses, pixels, False, tracks)
    free = _adjusted(K, size, poses, pixels, True, tracks)
    return FocalCheck(float(K[0, 0]), float(K[1, 1]), float(free[0][0, 0]), float(free[0][1, 1]), fixed[1], free[1],
                      principal_shift=float(np.hypot(*(free[0][:2, 2] - K[:2, 2]) / size[0])))


def _adjusted(K: np.ndarray, size: tuple[int, int], poses: np.ndarray, pixels: list[np.ndarray], free_intrinsics: bool,
              tracks: list[tuple[np.ndarray, list[tuple[int, int]]]]) -> tuple[np.ndarray, float]:
    """The (3, 3) camera matrix after a bundle adjustment of every pose and point (the gauge held by two
    keyframes; the focal lengths and principal point refined too with ``free_intrinsics``), and the median
    reprojection error of the observations then, px."""
    reconstruction = pycolmap.Reconstruction()
    reconstruction.add_camera_with_trivial_rig(pycolmap.Camera(
        camera_id=1, model="PINHOLE", width=size[0], height=size[1], params=[K[0, 0], K[1, 1], K[0, 2], K[1, 2]]))
    for n, (T, keypoints) in enumerate(zip(poses, pixels, strict=True), start=1):
        reconstruction.add_image_with_trivial_frame(pycolmap.Image(name=str(n), keypoints=keypoints, camera_id=1,
                                                                   image_id=n), pycolmap.Rigid3d(T[:3]))
    point_ids = []
    for position, observations in tracks:
        track = pycolmap.Track()
        for n, index in observations:
            track.add_element(n + 1, index)
        point_ids.append(reconstruction.add_point3D(position, track))
    options = pycolmap.BundleAdjustmentOptions()
    options.refine_focal_length = options.refine_principal_point = free_intrinsics
    options.refine_extra_params = False
    options.print_summary = False
    options.ceres.loss_function_type = pycolmap.LossFunctionType.HUBER
    options.ceres.loss_function_scale = HUBER_PX
    options.ceres.solver_options.max_num_iterations = 50
    options.ceres.solver_options.num_threads = 1
    config = pycolmap.BundleAdjustmentConfig()
    for n in range(1, len(poses) + 1):
        config.add_image(n)
    config.fix_gauge(pycolmap.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD)
    pycolmap.create_default_bundle_adjuster(options, config, reconstruction).solve()
    fx, fy, cx, cy = reconstruction.camera(1).params
    solved_K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    solved_poses = np.array([np.vstack([reconstruction.image(n).cam_from_world().matrix(), [0.0, 0.0, 0.0, 1.0]])
                             for n in range(1, len(poses) + 1)])
    positions = np.array([reconstruction.point3D(point_id).xyz for point_id in point_ids]).reshape(-1, 3)
    rows = [(n, index, p) for p, (_, observations) in enumerate(tracks) for n, index in observations]
    frames, indices, points = (np.array(column, np.int64) for column in zip(*rows, strict=True))
    observed = np.array([pixels[n][index] for n, index in zip(frames.tolist(), indices.tolist(), strict=True)])
    errors = reprojection_errors(solved_K, solved_poses[frames], positions[points], observed)
    return solved_K, float(np.median(errors))
