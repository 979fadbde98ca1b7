"""Extrinsic calibration of a multi-camera IR rig from a wand waved through its volume.

The wand carries three spheres on a line at unequal spacings (``Wand.spheres``, metres from its
first end). Each camera's blobs of a frame are identified as the wand's spheres (three blobs,
nearly collinear on ideal pinhole pixels; the middle one's position between the ends tells the
ends apart), then the chain is: essential matrix between the first camera and the camera that
shares most frames with it (USAC, then ``recoverPose``), triangulation, scale from the wand
length, PnP for every further camera, and a bundle adjustment over all camera poses and wand
positions in which the wand is rigid (one end, a direction, the known spacings), with a robust
loss on the pixel residuals. Intrinsics are known and held fixed.

Rig frame = the first camera's frame, unless ``floor_frame`` then ``reframe`` move it to a frame
set by three points (an L-frame, ordered by ``order_lframe``, or three spheres lying on the floor).
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy import sparse
from scipy.optimize import least_squares

from services.calibration.camera_info import CalibrationError
from services.geometry.absolute_orientation import three_point_transform
from services.geometry.camera import CameraModel, undistort_pixels
from services.geometry.rotation import matrix_from_rotvec, rotvec_from_matrix
from services.geometry.se3 import invert, make_transform
from services.geometry.triangulation import projection_matrix, triangulate_dlt

__all__ = ["Wand", "WandCalibration", "WandAdjustment", "identify_wand", "calibrate_wand", "floor_frame",
           "order_lframe", "reframe", "SKIP_REASONS"]

SKIP_REASONS = ("blob_count", "not_collinear", "too_short", "ambiguous_ends")
"""Why a camera's blobs of one frame were not taken as the wand."""

MIN_SHARED_FRAMES = 8
"""Frames a camera must share with the cameras already placed to be placed itself."""


@dataclass(frozen=True)
class Wand:
    """``spheres``: (3,) sphere positions along the wand, metres from its first end: 0, then increasing,
    the middle one off the centre so that the ends can be told apart."""

    spheres: np.ndarray

    def __post_init__(self) -> None:
        spheres = np.asarray(self.spheres, dtype=np.float64).ravel()
        if len(spheres) != 3 or spheres[0] != 0.0 or not np.all(np.diff(spheres) > 0):
            raise CalibrationError(f"wand spheres {spheres.tolist()}: need 3 positions in metres, 0 then increasing")
        if abs(spheres[1] / spheres[2] - 0.5) < 0.1:
            raise CalibrationError(f"wand spheres {spheres.tolist()}: the middle sphere must sit off the wand's "
                                   "centre (by at least a tenth of its length) for its ends to be told apart")
        object.__setattr__(self, "spheres", spheres)

    @property
    def length(self) -> float:
        """Distance between the end spheres, m."""
        return float(self.spheres[2])

    @property
    def ratio(self) -> float:
        """Middle sphere's distance from the first end over the length."""
        return float(self.spheres[1] / self.spheres[2])


def identify_wand(ideal_pixels: np.ndarray, wand: Wand, collinear_px: float = 2.0,
                  min_length_px: float = 20.0) -> tuple[np.ndarray | None, str]:
    """The wand's spheres among one camera's blobs of one frame: ``(order, "")`` or ``(None, reason)``.

    ``ideal_pixels``: (N, 2) blob centres as ideal pinhole pixels (distortion undone), in any
    order. ``order``: (3,) int indices into them, first end, middle, far end. Refused (reason
    from ``SKIP_REASONS``): other than three blobs; the middle one more than ``collinear_px`` from
    the line through the ends; ends closer than ``min_length_px``; the middle one's position
    between the ends less than halfway from the centre to the wand's own ratio (seen end-on,
    perspective can flip it).
    """
    pixels = np.asarray(ideal_pixels, dtype=np.float64).reshape(-1, 2)
    if len(pixels) != 3:
        return None, "blob_count"
    pairs = ((0, 1, 2), (0, 2, 1), (1, 2, 0))
    a, b, m = max(pairs, key=lambda p: float(np.linalg.norm(pixels[p[0]] - pixels[p[1]])))
    span = pixels[b] - pixels[a]
    length = float(np.linalg.norm(span))
    if length < min_length_px:
        return None, "too_short"
    offset = pixels[m] - pixels[a]
    if abs(span[0] * offset[1] - span[1] * offset[0]) / length > collinear_px:
        return None, "not_collinear"
    along = float(offset @ span) / length ** 2
    expected = wand.ratio
    if abs(along - 0.5) < 0.5 * abs(expected - 0.5):
        return None, "ambiguous_ends"
    first_is_a = (along < 0.5) == (expected < 0.5)
    return np.array([a, m, b] if first_is_a else [b, m, a]), ""


@dataclass(frozen=True)
class WandCalibration:
    """Result of ``calibrate_wand``.

    ``T_rig_camera``: (C, 4, 4), each camera's pose in the rig frame (the first camera's frame);
    ``wand_points``: (F, 3, 3) the adjusted spheres (first end, middle, far end) of the frames used,
    rig frame, m; ``frames``: (F,) their indices in the input; ``lengths``: (F,) the end-to-end
    length of each used frame triangulated sphere by sphere (no wand constraint) with the final
    poses, m; ``length_error_mean_mm`` / ``length_error_std_mm``: mean and standard deviation of
    ``lengths - wand.length``, mm; ``rms_px``: root mean square over the kept blob observations of
    the reprojection error's length after adjustment, px; ``frames_used`` (seen as the wand by two
    or more cameras) and ``frames_skipped``; ``skipped``: reason -> count over (frame, camera) pairs
    refused by ``identify_wand``; ``rejected``: frames dropped as outliers by the adjustment (counted
    in ``frames_skipped``); ``observations``: (C,) frames each camera contributed.
    """

    T_rig_camera: np.ndarray
    wand_points: np.ndarray
    frames: np.ndarray
    lengths: np.ndarray
    length_error_mean_mm: float
    length_error_std_mm: float
    rms_px: float
    frames_used: int
    frames_skipped: int
    skipped: dict[str, int] = field(default_factory=dict)
    rejected: int = 0
    observations: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))

    def report(self, names: Sequence[str]) -> str:
        """Lines for a person: each camera's pose in the rig frame, then the fit's figures."""
        lines = []
        for name, T, seen in zip(names, self.T_rig_camera, self.observations, strict=True):
            angle = np.degrees(np.linalg.norm(rotvec_from_matrix(T[:3, :3])))
            x, y, z = T[:3, 3]
            lines.append(f"{name}: position ({x:+.4f}, {y:+.4f}, {z:+.4f}) m, rotated {angle:.3f} deg, "
                         f"wand seen in {seen} frames")
        reasons = ", ".join(f"{reason} {n}" for reason, n in sorted(self.skipped.items())) or "none"
        lines += [f"wand length error {self.length_error_mean_mm:+.3f} mm mean, {self.length_error_std_mm:.3f} mm std "
                  f"(ends triangulated freely)",
                  f"reprojection RMS {self.rms_px:.3f} px",
                  f"frames used {self.frames_used}, skipped {self.frames_skipped} (outliers {self.rejected}); "
                  f"camera images refused: {reasons}"]
        return "\n".join(lines)


def calibrate_wand(cameras: Sequence[CameraModel], blobs: Sequence[Sequence[np.ndarray]], wand: Wand,
                   collinear_px: float = 2.0, outlier_px: float = 3.0, robust_px: float = 1.0) -> WandCalibration:
    """Extrinsics of ``cameras`` (their K and dist are used, their T_rig_camera ignored) from wand frames.

    ``blobs[f][c]``: (N, 2) blob centres, observed pixels of camera ``c`` in frame ``f``. A camera's
    frame is used when ``identify_wand`` accepts its blobs (``collinear_px``); a frame when two or
    more cameras saw the wand. A first adjustment with a Cauchy loss of scale ``robust_px`` finds the
    frames left with a residual over ``outlier_px`` in any camera (a false wand in one camera pulls
    the frame's wand off in the others too); the final one, without them, is plain least squares. CalibrationError
    when a camera cannot be placed (too few frames shared with the others) or too few frames are usable.
    """
    count = len(cameras)
    if count < 2:
        raise CalibrationError(f"wand calibration needs at least 2 cameras, got {count}")
    if any(len(frame) != count for frame in blobs):
        raise CalibrationError(f"every frame needs one blob list per camera ({count})")
    observed, skipped = _identify_all(cameras, blobs, wand, collinear_px)
    seen = ~np.isnan(observed[..., 0, 0])
    used = np.flatnonzero(seen.sum(axis=1) >= 2)
    if len(used) < MIN_SHARED_FRAMES:
        raise CalibrationError(f"only {len(used)} frames show the wand to two or more cameras; "
                               f"need at least {MIN_SHARED_FRAMES}")
    observed, seen = observed[used], seen[used]
    T_camera_rig = _initial_poses(cameras, observed, seen, wand)
    T_camera_rig, _, _, residuals = _adjust(cameras, observed, seen, wand, T_camera_rig, "cauchy", robust_px, 30)
    worst = np.zeros(seen.shape)
    worst[seen] = np.abs(residuals).max(axis=(1, 2))
    outliers = worst.max(axis=1) > outlier_px
    observed, seen, used = observed[~outliers], seen[~outliers], used[~outliers]
    T_camera_rig, ends, directions, residuals = _adjust(cameras, observed, seen, wand, T_camera_rig, "linear", 1.0, 100)
    points = ends[:, None, :] + wand.spheres[None, :, None] * directions[:, None, :]
    lengths = _free_lengths(cameras, observed, seen, T_camera_rig)
    errors_mm = (lengths - wand.length) * 1000.0
    return WandCalibration(
        T_rig_camera=np.array([invert(T) for T in T_camera_rig]), wand_points=points, frames=used, lengths=lengths,
        length_error_mean_mm=float(np.mean(errors_mm)), length_error_std_mm=float(np.std(errors_mm)),
        rms_px=float(np.sqrt(np.mean(np.sum(residuals ** 2, axis=2)))), frames_used=len(used),
        frames_skipped=len(blobs) - len(used), skipped=dict(skipped), rejected=int(np.sum(outliers)),
        observations=seen.sum(axis=0))


def _identify_all(cameras: Sequence[CameraModel], blobs: Sequence[Sequence[np.ndarray]], wand: Wand,
                  collinear_px: float) -> tuple[np.ndarray, Counter[str]]:
    """``(observed (F, C, 3, 2) observed pixels in wand order, NaN where not identified; reasons counted)``."""
    observed = np.full((len(blobs), len(cameras), 3, 2), np.nan)
    skipped: Counter[str] = Counter()
    for f, frame in enumerate(blobs):
        for c, (camera, pixels) in enumerate(zip(cameras, frame, strict=True)):
            pixels = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
            order, reason = identify_wand(undistort_pixels(pixels, camera.K, camera.dist), wand, collinear_px)
            if order is None:
                skipped[reason] += 1
            else:
                observed[f, c] = pixels[order]
    return observed, skipped


def _normalised(camera: CameraModel, pixels: np.ndarray) -> np.ndarray:
    """(N, 2) normalised image coordinates (x/z, y/z) of (N, 2) observed pixels."""
    return cv2.undistortPoints(pixels.reshape(-1, 1, 2), camera.K, camera.dist).reshape(-1, 2)


def _triangulate_frames(cameras: Sequence[CameraModel], observed: np.ndarray, seen: np.ndarray,
                        T_camera_rig: dict[int, np.ndarray]) -> np.ndarray:
    """(F, 3, 3) spheres triangulated (DLT, ideal pixels) from the placed cameras that saw them, NaN
    where fewer than two did; rig frame."""
    points = np.full((len(observed), 3, 3), np.nan)
    placed = sorted(T_camera_rig)
    projections = {c: projection_matrix(cameras[c].K, T_camera_rig[c]) for c in placed}
    ideal = {c: undistort_pixels(observed[:, c].reshape(-1, 2), cameras[c].K, cameras[c].dist).reshape(-1, 3, 2)
             for c in placed}
    for f in range(len(observed)):
        views = [c for c in placed if seen[f, c]]
        if len(views) < 2:
            continue
        for k in range(3):
            points[f, k] = triangulate_dlt(np.array([projections[c] for c in views]),
                                           np.array([ideal[c][f, k] for c in views]))
    return points


def _initial_poses(cameras: Sequence[CameraModel], observed: np.ndarray, seen: np.ndarray,
                   wand: Wand) -> np.ndarray:
    """(C, 4, 4) first ``T_camera_rig`` per camera: essential matrix for camera 0 and its best partner,
    scaled by the wand's median length, then PnP for the others (most shared frames first)."""
    count = len(cameras)
    shared = [int(np.sum(seen[:, 0] & seen[:, c])) for c in range(count)]
    partner = max(range(1, count), key=lambda c: shared[c])
    if shared[partner] < MIN_SHARED_FRAMES:
        raise CalibrationError(f"camera {cameras[0].name!r} shares at most {shared[partner]} wand frames with "
                               f"another camera; need at least {MIN_SHARED_FRAMES}")
    both = seen[:, 0] & seen[:, partner]
    x0 = _normalised(cameras[0], observed[both, 0].reshape(-1, 2))
    x1 = _normalised(cameras[partner], observed[both, partner].reshape(-1, 2))
    focal = float(np.mean([cameras[0].K[0, 0], cameras[partner].K[0, 0]]))
    E, mask = cv2.findEssentialMat(x0, x1, np.eye(3), method=cv2.USAC_ACCURATE, prob=0.9999,
                                   threshold=1.0 / focal)
    if E is None or E.shape != (3, 3):
        raise CalibrationError(f"no essential matrix between {cameras[0].name!r} and {cameras[partner].name!r}")
    _, R, t, _ = cv2.recoverPose(E, x0, x1, np.eye(3), mask=mask)
    T_camera_rig = {0: np.eye(4), partner: make_transform(R, t.ravel())}
    points = _triangulate_frames(cameras, observed, seen, T_camera_rig)
    scale = wand.length / float(np.nanmedian(np.linalg.norm(points[:, 2] - points[:, 0], axis=1)))
    T_camera_rig[partner][:3, 3] *= scale
    points *= scale
    while len(T_camera_rig) < count:
        known = ~np.isnan(points[:, 0, 0])
        left = [c for c in range(count) if c not in T_camera_rig]
        overlap = {c: int(np.sum(known & seen[:, c])) for c in left}
        c = max(left, key=lambda k: overlap[k])
        if overlap[c] < MIN_SHARED_FRAMES:
            raise CalibrationError(f"camera {cameras[c].name!r} shares {overlap[c]} wand frames with the cameras "
                                   f"placed before it; need at least {MIN_SHARED_FRAMES}")
        rows = known & seen[:, c]
        ok, rvec, tvec, _ = cv2.solvePnPRansac(points[rows].reshape(-1, 3), observed[rows, c].reshape(-1, 2),
                                               cameras[c].K, cameras[c].dist, reprojectionError=3.0,
                                               confidence=0.999, iterationsCount=500, flags=cv2.SOLVEPNP_SQPNP)
        if not ok:
            raise CalibrationError(f"camera {cameras[c].name!r}: no pose fits the wand points it saw")
        T_camera_rig[c] = make_transform(matrix_from_rotvec(rvec.ravel()), tvec.ravel())
        points = _triangulate_frames(cameras, observed, seen, T_camera_rig)
    return np.array([T_camera_rig[c] for c in range(count)])


class WandAdjustment:
    """The bundle-adjustment problem of ``calibrate_wand``: cameras 1.. (camera 0 is the rig frame) and
    one rigid wand per frame, against the observed pixels, with an analytic sparse Jacobian.

    Parameters ``x``: per camera 1.., its ``T_camera_rig`` as a rotation vector and a translation (6);
    then per frame the wand's first end ``e`` (3,) and two steps ``(a, b)`` of its direction in the
    plane normal to its start ``d0``: ``d = normalise(d0 + a u + b v)``; sphere k is at
    ``e + spheres[k] d``. Residuals: projected - observed px of the seen (frame, camera) pairs in
    row-major order, (M, 3, 2) flattened.
    """

    def __init__(self, cameras: Sequence[CameraModel], observed: np.ndarray, seen: np.ndarray, wand: Wand,
                 T_camera_rig: np.ndarray):
        self.cameras, self.observed, self.spheres = cameras, observed, wand.spheres
        self.count, self.frames = len(cameras), len(observed)
        start = _triangulate_frames(cameras, observed, seen, {c: T_camera_rig[c] for c in range(self.count)})
        direction0 = start[:, 2] - start[:, 0]
        self.direction0 = direction0 / np.linalg.norm(direction0, axis=1, keepdims=True)
        helper = np.where(np.abs(self.direction0[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
        u = np.cross(self.direction0, helper)
        self.u = u / np.linalg.norm(u, axis=1, keepdims=True)
        self.v = np.cross(self.direction0, self.u)
        self.pairs = np.argwhere(seen)
        self.camera_params = 6 * (self.count - 1)
        ends = start.mean(axis=1) - wand.spheres.mean() * self.direction0
        self.x0 = np.concatenate([np.concatenate([np.concatenate([rotvec_from_matrix(T[:3, :3]), T[:3, 3]])
                                                  for T in T_camera_rig[1:]]),
                                  np.hstack([ends, np.zeros((self.frames, 2))]).ravel()])

    def unpack(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``(poses (C-1, 6), ends (F, 3), directions (F, 3) unit, unnormalised directions (F, 3))``."""
        poses = x[:self.camera_params].reshape(-1, 6)
        wands = x[self.camera_params:].reshape(self.frames, 5)
        n = self.direction0 + wands[:, 3:4] * self.u + wands[:, 4:5] * self.v
        return poses, wands[:, :3], n / np.linalg.norm(n, axis=1, keepdims=True), n

    def poses(self, x: np.ndarray) -> np.ndarray:
        """(C, 4, 4) ``T_camera_rig``."""
        return np.array([np.eye(4)] + [make_transform(matrix_from_rotvec(p[:3]), p[3:]) for p in self.unpack(x)[0]])

    def _project(self, x: np.ndarray, with_jacobian: bool) -> tuple[np.ndarray, sparse.csr_matrix | None]:
        poses, ends, d, n = self.unpack(x)
        points = ends[:, None, :] + self.spheres[None, :, None] * d[:, None, :]
        out = np.empty((len(self.pairs), 3, 2))
        rows_list, cols_list, values_list = [], [], []
        if with_jacobian:
            # d d / d(a, b) = (I - d d^T) / |n| [u v], per frame (F, 3, 2)
            normal = (np.eye(3)[None] - d[:, :, None] * d[:, None, :]) / np.linalg.norm(n, axis=1)[:, None, None]
            d_direction = normal @ np.stack([self.u, self.v], axis=2)
        for c, camera in enumerate(self.cameras):
            index = np.flatnonzero(self.pairs[:, 1] == c)
            frames = self.pairs[index, 0]
            rvec, tvec = (np.zeros(3), np.zeros(3)) if c == 0 else (poses[c - 1, :3], poses[c - 1, 3:])
            projected, jacobian = cv2.projectPoints(points[frames].reshape(-1, 3), rvec, tvec, camera.K, camera.dist)
            out[index] = projected.reshape(-1, 3, 2) - self.observed[frames, c]
            if not with_jacobian:
                continue
            jacobian = jacobian.reshape(len(index), 3, 2, -1)
            d_point = jacobian[..., 3:6] @ matrix_from_rotvec(rvec)  # (m, 3, 2, 3), pixels per world metre
            d_ab = d_point @ (self.spheres[None, :, None, None] * d_direction[frames][:, None])  # (m, 3, 2, 2)
            block = np.concatenate([d_point, d_ab], axis=3).reshape(len(index), 6, 5)
            wand_cols = self.camera_params + 5 * frames[:, None, None] + np.arange(5)[None, None, :]
            obs_rows = 6 * index[:, None, None] + np.arange(6)[None, :, None]
            rows_list.append(np.broadcast_to(obs_rows, block.shape).ravel())
            cols_list.append(np.broadcast_to(wand_cols, block.shape).ravel())
            values_list.append(block.ravel())
            if c > 0:
                block = jacobian[..., :6].reshape(len(index), 6, 6)
                rows_list.append(np.broadcast_to(obs_rows, block.shape).ravel())
                cols_list.append(np.broadcast_to(6 * (c - 1) + np.arange(6)[None, None, :], block.shape).ravel())
                values_list.append(block.ravel())
        if not with_jacobian:
            return out.ravel(), None
        shape = (6 * len(self.pairs), len(self.x0))
        return out.ravel(), sparse.csr_matrix((np.concatenate(values_list), (np.concatenate(rows_list),
                                                                             np.concatenate(cols_list))), shape=shape)

    def residuals(self, x: np.ndarray) -> np.ndarray:
        """(6M,) projected - observed px."""
        return self._project(x, False)[0]

    def jacobian(self, x: np.ndarray) -> sparse.csr_matrix:
        """(6M, len(x)) sparse derivatives of ``residuals`` with respect to ``x``."""
        jacobian = self._project(x, True)[1]
        assert jacobian is not None
        return jacobian


def _adjust(cameras: Sequence[CameraModel], observed: np.ndarray, seen: np.ndarray, wand: Wand,
            T_camera_rig: np.ndarray, loss: str, robust_px: float,
            iterations: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``WandAdjustment`` solved with ``loss`` (a least_squares loss of scale ``robust_px``) in at most
    ``iterations`` steps; returns
    ``(T_camera_rig (C, 4, 4), ends (F, 3), directions (F, 3), residuals (M, 3, 2) px)``."""
    problem = WandAdjustment(cameras, observed, seen, wand, T_camera_rig)
    solution = least_squares(problem.residuals, problem.x0, jac=problem.jacobian, loss=loss, f_scale=robust_px,
                             x_scale="jac", method="trf", xtol=1e-10, ftol=1e-10, max_nfev=iterations,
                             tr_options={"atol": 1e-12, "btol": 1e-12})
    _, ends, d, _ = problem.unpack(solution.x)
    return problem.poses(solution.x), ends, d, problem.residuals(solution.x).reshape(-1, 3, 2)


def _free_lengths(cameras: Sequence[CameraModel], observed: np.ndarray, seen: np.ndarray,
                  T_camera_rig: np.ndarray) -> np.ndarray:
    """(F,) end-to-end lengths, m, of each frame's spheres triangulated one by one (no wand constraint)."""
    points = _triangulate_frames(cameras, observed, seen, {c: T_camera_rig[c] for c in range(len(cameras))})
    return np.linalg.norm(points[:, 2] - points[:, 0], axis=1)


def floor_frame(origin: np.ndarray, on_x: np.ndarray, in_plane: np.ndarray) -> np.ndarray:
    """(4, 4) ``T_rig_floor`` of the frame three points set (an L-frame's spheres or three on the floor).

    ``origin``, ``on_x``, ``in_plane``: (3,) rig frame, m. Floor frame: origin at ``origin``, x
    towards ``on_x``, y in the plane of the three points on the side of ``in_plane``, z = x cross y
    (normal to the floor). Points on one line give CalibrationError.
    """
    points = np.array([origin, on_x, in_plane], dtype=np.float64).reshape(3, 3)
    x, p = points[1] - points[0], points[2] - points[0]
    along = float(x @ p) / max(float(np.linalg.norm(x)), 1e-300)
    across = float(np.sqrt(max(float(p @ p) - along ** 2, 0.0)))
    in_floor = np.array([[0.0, 0.0, 0.0], [np.linalg.norm(x), 0.0, 0.0], [along, across, 0.0]])
    try:
        return three_point_transform(in_floor, points)
    except ValueError as exc:
        raise CalibrationError("floor frame: the three points lie on one line") from exc


def order_lframe(points: np.ndarray, right_angle_tolerance_deg: float = 10.0) -> np.ndarray:
    """(3, 3) the spheres of an L-frame (rows, any order, m) as corner, long arm's end, short arm's end.

    The corner is the sphere whose angle is nearest 90 deg; CalibrationError when that angle is off
    by more than ``right_angle_tolerance_deg`` or the arms differ by less than a tenth of the longer.
    """
    points = np.asarray(points, dtype=np.float64).reshape(3, 3)

    def angle(k: int) -> float:
        a, b = points[(k + 1) % 3] - points[k], points[(k + 2) % 3] - points[k]
        return float(np.degrees(np.arccos(np.clip(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)), -1.0, 1.0))))

    corner = min(range(3), key=lambda k: abs(angle(k) - 90.0))
    if abs(angle(corner) - 90.0) > right_angle_tolerance_deg:
        raise CalibrationError(f"L-frame: no right angle among its spheres (nearest {angle(corner):.1f} deg)")
    ends = [points[(corner + 1) % 3], points[(corner + 2) % 3]]
    arms = [float(np.linalg.norm(e - points[corner])) for e in ends]
    if abs(arms[0] - arms[1]) < 0.1 * max(arms):
        raise CalibrationError(f"L-frame: its arms ({arms[0]:.3f} and {arms[1]:.3f} m) are too alike to tell x from y")
    long, short = (0, 1) if arms[0] > arms[1] else (1, 0)
    return np.array([points[corner], ends[long], ends[short]])


def reframe(T_rig_camera: np.ndarray, T_rig_new: np.ndarray) -> np.ndarray:
    """(C, 4, 4) the cameras' poses ``T_new_camera`` in a new rig frame given as ``T_rig_new`` (4, 4)."""
    return invert(T_rig_new)[None] @ np.asarray(T_rig_camera, dtype=np.float64)
