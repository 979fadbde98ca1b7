"""Local bundle adjustment and pose-only refinement for monocular SLAM, solved by Ceres through pycolmap.

Frames and units: OpenCV camera frames; a pose ``T_camera_world`` (4, 4) maps world points into a
keyframe's camera frame; world units are the map's (monocular scale is arbitrary); pixels are
undistorted and projected by the pinhole ``K`` (3, 3).

Cost: each observation's reprojection error ``e = project(K, T X) - pixel`` (2,), whitened by its
sigma (px), under a Huber loss on the whitened squared norm ``s = |e / sigma|^2``:
``rho(s) = s`` for ``s <= h^2``, ``2 h sqrt(s) - h^2`` beyond, with ``h = huber_px`` (so the bend
lies at ``huber_px * sigma`` pixels); the solver minimises ``0.5 * sum(rho)``. The default
``h = sqrt(5.991)`` puts the bend at the 95 % chi-square bound of two degrees of freedom, the bound
that classifies outliers after the solve (ORB-SLAM's choice).

pycolmap has no per-observation weight (its bundle adjuster applies one loss to every residual). The
whitening is exact all the same: an observation of sigma ``s`` is given to a camera whose intrinsics
are ``K`` divided by ``s`` (fx, fy, cx, cy) at the pixel divided by ``s``, so its residual is
``e / s``. Each distinct sigma (a pyramid level) gets such a camera, and the cameras form a rig
whose sensors all sit at the identity (held constant); a keyframe is a frame of that rig holding one
image per sigma it has observations at, so all of them share the keyframe's one pose. Without
sigmas there is one camera and one image per keyframe.

Gauge: a monocular map is fixed only up to a similarity (rotation, translation and scale). The
caller fixes it through ``BundleProblem.fixed``: two or more observed fixed keyframes with distinct
centres fix all seven degrees of freedom; with one, scale is left free unless ``fix_scale=True``.
Then the solver holds one translation coordinate of one free keyframe constant (pycolmap's
``TWO_CAMS_FROM_WORLD`` gauge), which ties the scale to that keyframe's offset from the fixed one.
When the solve so changes the window's scale by more than ``MAX_RESCALE`` (the keyframe sat a few
millimetres from the fixed one and its offset was poorly known), the solution is scaled back about the
fixed keyframe's centre so that the free keyframes lie as far from it, in sum, as they did. Without any
observed fixed keyframe the problem is refused.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
import pycolmap

from services.geometry.refine import augmented_rows, damped_steps, increments, normal_equations, point_basis
from services.geometry.se3 import check_transform
from services.geometry.shapes import check_shape

__all__ = ["CHI2_2DOF_95", "HUBER_PX", "BundleProblem", "BundleResult", "PoseRefinement", "bundle_adjust",
           "refine_pose", "reprojection_errors"]

CHI2_2DOF_95 = 5.991
"""95 % quantile of the chi-square distribution with two degrees of freedom: an observation whose
``(error / sigma)^2`` exceeds it is an outlier."""
HUBER_PX = math.sqrt(CHI2_2DOF_95)
"""Default Huber bend of the whitened error (2.4477)."""
MAX_RESCALE = 0.1
"""Largest change of a window's scale (a fraction) that a solve with one fixed keyframe may make
(``bundle_adjust``'s ``fix_scale``); a larger one is the gauge's, and undone."""


@dataclass(frozen=True)
class BundleProblem:
    """A local bundle adjustment: keyframe poses and points to refine from M observations.

    ``K``: (3, 3) float64 pinhole, pixels undistorted. ``poses``: keyframe id -> (4, 4)
    ``T_camera_world``. ``points``: point id -> (3,) world. ``frame_ids``, ``point_ids``: (M,) int64,
    the keyframe and point of each observation; ``pixels``: (M, 2) float64 observed pixels;
    ``fixed``: keyframe ids whose pose stays put (the gauge, and keyframes outside the window);
    ``sigmas``: (M,) pixel standard deviation of each observation (the pyramid level's scale), None
    for all 1.
    """

    K: np.ndarray
    poses: dict[int, np.ndarray]
    points: dict[int, np.ndarray]
    frame_ids: np.ndarray
    point_ids: np.ndarray
    pixels: np.ndarray
    fixed: frozenset[int]
    sigmas: np.ndarray | None = None


@dataclass(frozen=True)
class BundleResult:
    """``poses``, ``points``: every pose and point of the problem, optimised (fixed poses, and points
    with fewer than two observations, as given). ``errors_px``: (M,) reprojection error (px) of each
    observation after the solve, infinite behind the camera; ``outliers``: (M,) bool, chi-square
    above ``CHI2_2DOF_95`` on ``(error / sigma)^2`` or behind the camera. ``initial_rms_px`` and
    ``final_rms_px``: root mean square reprojection error (px) of the final inliers before and after
    the solve (NaN when there are none); ``iterations``: Ceres's iterations (steps tried, accepted or not);
    ``seconds``: wall time of the whole call."""

    poses: dict[int, np.ndarray]
    points: dict[int, np.ndarray]
    errors_px: np.ndarray
    outliers: np.ndarray
    initial_rms_px: float
    final_rms_px: float
    iterations: int
    seconds: float


@dataclass(frozen=True)
class PoseRefinement:
    """``T_camera_world`` (4, 4) refined; ``inliers`` (N,) bool by the chi-square test of
    ``BundleResult.outliers``; ``rms_px``: reprojection RMS (px) of the inliers (NaN without any)."""

    T_camera_world: np.ndarray
    inliers: np.ndarray
    rms_px: float


@dataclass(frozen=True)
class _Observations:
    """A problem checked and indexed. ``keyframes`` (F,) int64 ids of the observed keyframes, sorted;
    ``poses`` (F, 4, 4) their start; ``fixed`` (F,) bool. ``point_keys`` (P,) int64 ids of every point
    of the problem, ``positions`` (P, 3) their start. Per observation (M,): ``frame_rows`` into
    ``keyframes``, ``point_rows`` into ``point_keys``, ``sigmas``; ``pixels`` (M, 2)."""

    keyframes: np.ndarray
    poses: np.ndarray
    fixed: np.ndarray
    point_keys: np.ndarray
    positions: np.ndarray
    frame_rows: np.ndarray
    point_rows: np.ndarray
    pixels: np.ndarray
    sigmas: np.ndarray


def reprojection_errors(K: np.ndarray, T_camera_world: np.ndarray, points_world: np.ndarray,
                        pixels: np.ndarray) -> np.ndarray:
    """(N,) pixel distance between (N, 2) ``pixels`` and the projections of (N, 3) world points by
    per-point poses (N, 4, 4) ``T_camera_world`` (or one (4, 4) pose) and a zero-skew pinhole ``K``;
    infinite where a point is not in front of its camera."""
    T = np.asarray(T_camera_world, dtype=np.float64)
    points = np.asarray(points_world, dtype=np.float64)
    if T.ndim == 2:
        camera = points @ T[:3, :3].T + T[:3, 3]
    else:
        camera = np.einsum("mij,mj->mi", T[:, :3, :3], points) + T[:, :3, 3]
    depth = camera[:, 2]
    front = depth > 0
    safe = np.where(front, depth, 1.0)[:, None]
    projected = camera[:, :2] / safe * K[[0, 1], [0, 1]] + K[:2, 2]
    return np.where(front, np.linalg.norm(projected - pixels, axis=1), np.inf)


def _rms(errors: np.ndarray) -> float:
    return float(np.sqrt(np.mean(errors ** 2))) if len(errors) else math.nan


def _check_K(K: np.ndarray) -> np.ndarray:
    K = check_shape(K, "3,3", "K", np.float64)
    if not np.all(np.isfinite(K)):
        raise ValueError("K must be finite")
    if np.any(K[[0, 1, 2, 2, 2], [1, 0, 0, 1, 2]] != (0, 0, 0, 0, 1)) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise ValueError("K must be a zero-skew pinhole matrix [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0")
    return K


def _check_sigmas(sigmas: np.ndarray | None, count: int) -> np.ndarray:
    if sigmas is None:
        return np.ones(count)
    sigmas = check_shape(sigmas, f"{count}", "sigmas", np.float64)
    if not np.all(np.isfinite(sigmas) & (sigmas > 0)):
        raise ValueError("sigmas must be positive finite pixels")
    return sigmas


def _stacked_points(points: dict[int, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """``(keys, positions)``: (P,) int64 ids and (P, 3) float64 positions of ``points``; ValueError naming
    the first that is not a finite (3,) vector."""
    keys = np.fromiter(points, dtype=np.int64, count=len(points))
    try:
        positions = np.array(list(points.values()), dtype=np.float64).reshape(len(keys), 3)
    except ValueError:
        positions = np.full((len(keys), 3), np.nan)
    if not np.all(np.isfinite(positions)):
        for key, X in points.items():
            if not np.all(np.isfinite(check_shape(X, "3", f"points[{key}]", np.float64))):
                raise ValueError(f"points[{key}] must be finite")
    return keys, positions


def _rows(ids: np.ndarray, keys: np.ndarray, name: str, what: str) -> np.ndarray:
    """Row of each of ``ids`` in the sorted ``keys``; ValueError listing ids that are not there."""
    rows = np.minimum(np.searchsorted(keys, ids), max(len(keys) - 1, 0))
    missing = (keys[rows] != ids) if len(keys) else np.ones(len(ids), dtype=bool)
    if missing.any():
        unknown = np.unique(ids[missing]).tolist()
        raise ValueError(f"{name} names ids with no {what}: {unknown[:5]}{' ...' if len(unknown) > 5 else ''}")
    return rows


def _check_problem(problem: BundleProblem) -> _Observations:
    """The problem checked and indexed; ValueError naming the first thing wrong."""
    _check_K(problem.K)
    frame_ids = np.asarray(problem.frame_ids)
    point_ids = np.asarray(problem.point_ids)
    pixels = check_shape(problem.pixels, "M,2", "pixels", np.float64)
    count = len(pixels)
    if count == 0 or not np.all(np.isfinite(pixels)):
        raise ValueError(f"pixels must be finite with M >= 1, got {count} rows")
    for name, ids in (("frame_ids", frame_ids), ("point_ids", point_ids)):
        if not np.issubdtype(check_shape(ids, f"{count}", name).dtype, np.integer):
            raise ValueError(f"{name} must be integers, got {ids.dtype}")
    sigmas = _check_sigmas(problem.sigmas, count)
    for key, T in problem.poses.items():
        check_transform(T, f"poses[{key}]")
    point_keys, positions = _stacked_points(problem.points)
    pose_keys = np.sort(np.fromiter(problem.poses, dtype=np.int64, count=len(problem.poses)))
    _rows(frame_ids, pose_keys, "frame_ids", "pose")
    _rows(np.array(sorted(problem.fixed), dtype=np.int64), pose_keys, "fixed", "pose")
    order = np.argsort(point_keys)
    point_rows = order[_rows(point_ids, point_keys[order], "point_ids", "point")]
    keyframes, frame_rows = np.unique(frame_ids.astype(np.int64), return_inverse=True)
    fixed = np.isin(keyframes, np.array(sorted(problem.fixed), dtype=np.int64))
    if fixed.all():
        raise ValueError("no free pose: every observed keyframe is in fixed, nothing would move")
    if not fixed.any():
        raise ValueError("no observed keyframe is fixed: the map's frame (the gauge) would float; fix at least one")
    poses = np.stack([np.asarray(problem.poses[k], dtype=np.float64) for k in keyframes.tolist()])
    return _Observations(keyframes, poses, fixed, point_keys, positions, frame_rows, point_rows, pixels, sigmas)


@dataclass(frozen=True)
class _Scene:
    """A pycolmap reconstruction of a problem: pycolmap frame id ``f + 1`` holds observed keyframe row
    ``f``; ``points`` maps rows of ``point_keys`` seen at least twice to pycolmap point ids; the image
    and camera ids."""

    reconstruction: pycolmap.Reconstruction
    points: dict[int, int]
    images: list[int]
    cameras: list[int]


def _scene(K: np.ndarray, observations: _Observations) -> _Scene:
    """The reconstruction the module docstring describes: one camera per distinct sigma in one rig,
    one frame per observed keyframe, one image per keyframe and sigma, one 3D point per point seen
    at least twice (pycolmap refuses shorter tracks; a free point seen once constrains nothing). The
    rig's reference camera is the sigma observed most often: Ceres evaluates its observations' cost
    without composing the rig offset, several times faster."""
    sigmas, level, counts = np.unique(observations.sigmas, return_inverse=True, return_counts=True)
    busiest_first = np.argsort(-counts, kind="stable")
    sigmas, level = sigmas[busiest_first], np.argsort(busiest_first)[level]
    reconstruction = pycolmap.Reconstruction()
    rig = pycolmap.Rig(rig_id=1)
    for index, sigma in enumerate(sigmas.tolist()):
        camera = pycolmap.Camera(camera_id=index + 1, model="PINHOLE", width=max(1, round(2 * K[0, 2] / sigma)),
                                 height=max(1, round(2 * K[1, 2] / sigma)),
                                 params=[K[0, 0] / sigma, K[1, 1] / sigma, K[0, 2] / sigma, K[1, 2] / sigma])
        reconstruction.add_camera(camera)
        if index == 0:
            rig.add_ref_sensor(camera.sensor_id)
        else:
            rig.add_sensor(camera.sensor_id, pycolmap.Rigid3d())
    reconstruction.add_rig(rig)
    order = np.lexsort((level, observations.frame_rows))
    keys = np.stack([observations.frame_rows[order], level[order]], axis=1)
    starts = np.flatnonzero(np.r_[True, np.any(keys[1:] != keys[:-1], axis=1), True])
    image_of, slot_of = np.empty(len(order), dtype=np.int64), np.empty(len(order), dtype=np.int64)
    images_of_frame: dict[int, list[pycolmap.Image]] = {}
    for image_id, (start, stop) in enumerate(zip(starts[:-1].tolist(), starts[1:].tolist(), strict=True), start=1):
        members = order[start:stop]
        row, camera_index = keys[start].tolist()
        image = pycolmap.Image(name=str(image_id), keypoints=observations.pixels[members] / sigmas[camera_index],
                               camera_id=camera_index + 1, image_id=image_id)
        image.frame_id = row + 1
        images_of_frame.setdefault(row + 1, []).append(image)
        image_of[members], slot_of[members] = image_id, np.arange(stop - start)
    for frame_id, images in images_of_frame.items():
        frame = pycolmap.Frame(frame_id=frame_id, rig_id=1,
                               rig_from_world=pycolmap.Rigid3d(observations.poses[frame_id - 1, :3]))
        for image in images:
            frame.add_data_id(image.data_id)
        reconstruction.add_frame(frame)
        for image in images:
            reconstruction.add_image(image)
        reconstruction.register_frame(frame_id)
    by_point = np.argsort(observations.point_rows, kind="stable")
    rows = observations.point_rows[by_point]
    bounds = np.flatnonzero(np.r_[True, rows[1:] != rows[:-1], True]).tolist()
    image_list, slot_list, row_list = image_of[by_point].tolist(), slot_of[by_point].tolist(), rows.tolist()
    points: dict[int, int] = {}
    for start, stop in zip(bounds[:-1], bounds[1:], strict=True):
        if stop - start < 2:
            continue
        track = pycolmap.Track()
        for k in range(start, stop):
            track.add_element(image_list[k], slot_list[k])
        points[row_list[start]] = reconstruction.add_point3D(observations.positions[row_list[start]], track)
    return _Scene(reconstruction, points, list(range(1, len(starts))), list(range(1, len(sigmas) + 1)))


def _options(max_iterations: int, huber_px: float, tolerance: float) -> pycolmap.BundleAdjustmentOptions:
    """Ceres options: intrinsics and rig offsets constant, Huber at ``huber_px``, stop when an iteration
    lowers the cost by less than ``tolerance`` of it, silent, one thread (1 thread beat 2 on 20-camera
    problems, and the cores are shared with tracking)."""
    options = pycolmap.BundleAdjustmentOptions()
    options.refine_focal_length = options.refine_principal_point = options.refine_extra_params = False
    options.refine_sensor_from_rig = False
    options.print_summary = False
    options.ceres.loss_function_type = pycolmap.LossFunctionType.HUBER
    options.ceres.loss_function_scale = huber_px
    options.ceres.solver_options.max_num_iterations = max_iterations
    options.ceres.solver_options.function_tolerance = tolerance
    options.ceres.solver_options.num_threads = 1
    return options


def bundle_adjust(problem: BundleProblem, *, max_iterations: int = 20, huber_px: float = HUBER_PX,
                  fix_scale: bool = False, tolerance: float = 1e-6) -> BundleResult:
    """Refine the free poses and the points of ``problem`` to minimise the robust whitened reprojection
    cost of the module docstring, by Ceres (Levenberg-Marquardt, Schur complement) through pycolmap.

    Keyframes in ``problem.fixed`` keep their pose; the rest of the gauge is the caller's to fix (module
    docstring): ``fix_scale`` holds the scale when only one keyframe is fixed. Points seen once are not
    optimised. ``max_iterations`` bounds Ceres's iterations; it stops earlier when an iteration lowers
    the cost by less than ``tolerance`` of it (under a robust loss the last digits crawl). Raises
    ValueError, naming the problem, on malformed arrays, ids without a pose or point, no free observed
    keyframe or no fixed one.
    """
    start = time.perf_counter()
    observations = _check_problem(problem)
    if max_iterations < 1 or not huber_px > 0:
        raise ValueError(f"max_iterations must be >= 1 and huber_px > 0, got {max_iterations} and {huber_px}")
    K = _check_K(problem.K)
    scene = _scene(K, observations)
    config = pycolmap.BundleAdjustmentConfig()
    for image_id in scene.images:
        config.add_image(image_id)
    for camera_id in scene.cameras:
        config.set_constant_cam_intrinsics(camera_id)
    for row in np.flatnonzero(observations.fixed).tolist():
        config.set_constant_rig_from_world_pose(row + 1)
    if fix_scale:
        config.fix_gauge(pycolmap.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD)
    summary = pycolmap.create_default_bundle_adjuster(_options(max_iterations, huber_px, tolerance), config,
                                                      scene.reconstruction).solve()
    ceres = getattr(summary, "ceres_summary", None)
    reconstruction = scene.reconstruction
    solved_poses = observations.poses.copy()
    for row in np.flatnonzero(~observations.fixed).tolist():
        rig_from_world = reconstruction.frame(row + 1).rig_from_world
        assert rig_from_world is not None
        solved_poses[row, :3] = rig_from_world.matrix()
    positions = observations.positions.copy()
    for row, point_id in scene.points.items():
        positions[row] = reconstruction.point3D(point_id).xyz
    if fix_scale and np.count_nonzero(observations.fixed) == 1:
        _hold_scale(observations, solved_poses, positions, np.fromiter(scene.points, np.int64))
    frame_rows, point_rows = observations.frame_rows, observations.point_rows
    errors = reprojection_errors(K, solved_poses[frame_rows], positions[point_rows], observations.pixels)
    outliers = ~((errors / observations.sigmas) ** 2 <= CHI2_2DOF_95)
    before = reprojection_errors(K, observations.poses[frame_rows], observations.positions[point_rows],
                                 observations.pixels)
    poses = {key: np.array(T, dtype=np.float64) for key, T in problem.poses.items()}
    poses.update(zip(observations.keyframes.tolist(), solved_poses, strict=True))
    return BundleResult(poses, dict(zip(observations.point_keys.tolist(), positions, strict=True)), errors, outliers,
                        _rms(before[~outliers]), _rms(errors[~outliers]),
                        0 if ceres is None else int(ceres.num_successful_steps + ceres.num_unsuccessful_steps) - 1,
                        time.perf_counter() - start)


def _hold_scale(observations: _Observations, poses: np.ndarray, positions: np.ndarray, rows: np.ndarray) -> None:
    """Undo, in place, a rescaling of the window by more than ``MAX_RESCALE`` that the solver's gauge made:
    ``poses`` (F, 4, 4) solved ``T_camera_world`` of the observed keyframes and ``positions`` (P, 3) solved
    points (rows ``rows`` optimised, the others seen once and left as given) are scaled about the one fixed
    keyframe's centre so that the free keyframes' centres lie as far from it, in sum, as before the solve.

    With one fixed keyframe every such scale has the same cost. The solver's gauge holds one coordinate of
    one free keyframe, the map's second: that anchors the scale to the initial map, so it does not drift
    with the tracker's, but when that keyframe sits a few millimetres from the first its offset is poorly
    known, and a change of it within its uncertainty rescales the whole window (and the frames tracked next
    jump with it). The sum of distances is led by the keyframes furthest away, whose distances are known best."""
    free = ~observations.fixed
    T_fixed = observations.poses[np.flatnonzero(observations.fixed)[0]]
    centre = -T_fixed[:3, :3].T @ T_fixed[:3, 3]
    before = np.linalg.norm(_centres(observations.poses[free]) - centre, axis=1).sum()
    after = np.linalg.norm(_centres(poses[free]) - centre, axis=1).sum()
    if not (before > 0 and after > 0) or abs(math.log(before / after)) <= math.log1p(MAX_RESCALE):
        return
    scale = before / after
    positions[rows] = centre + scale * (positions[rows] - centre)
    moved = centre + scale * (_centres(poses[free]) - centre)
    poses[free, :3, 3] = -np.einsum("fij,fj->fi", poses[free, :3, :3], moved)


def _centres(T_camera_world: np.ndarray) -> np.ndarray:
    """(F, 3) world centres of the cameras of (F, 4, 4) ``T_camera_world``."""
    return -np.einsum("fji,fj->fi", T_camera_world[:, :3, :3], T_camera_world[:, :3, 3])


def _robust_cost(errors: np.ndarray, sigmas: np.ndarray, huber_px: float) -> float:
    """``0.5 * sum(rho(s))`` of the whitened squared errors (infinite when a point is behind)."""
    squared = (errors / sigmas) ** 2
    bent = np.where(squared <= huber_px ** 2, squared, 2 * huber_px * np.sqrt(squared) - huber_px ** 2)
    return float(0.5 * np.sum(bent))


def _refine_round(K: np.ndarray, T: np.ndarray, points: np.ndarray, pixels: np.ndarray, sigmas: np.ndarray,
                  huber_px: float, max_iterations: int) -> np.ndarray:
    """``T`` (4, 4) lowering the robust cost of these observations: Levenberg-Marquardt on the
    iteratively reweighted normal equations (Huber weights ``rho'(s)`` over ``sigma^2``), a step
    kept only when it lowers the robust cost itself."""
    basis = point_basis(points[None])
    cost = _robust_cost(reprojection_errors(K, T, points, pixels), sigmas, huber_px)
    damping = 1e-3
    for _ in range(max_iterations):
        rows, _ = augmented_rows(T[None], basis, pixels[None], K)
        squared = np.sum((rows[0, :, :, 6] / sigmas[:, None]) ** 2, axis=1)
        weights = np.where(squared <= huber_px ** 2, 1.0, huber_px / np.sqrt(np.maximum(squared, 1e-300)))
        rows *= (np.sqrt(weights) / sigmas)[None, :, None, None]
        normal = normal_equations(rows)
        while damping < 1e12:
            steps, singular = damped_steps(normal, np.array([damping]))
            if singular:
                return T
            candidate = T @ increments(steps)[0]
            candidate_cost = _robust_cost(reprojection_errors(K, candidate, points, pixels), sigmas, huber_px)
            if candidate_cost < cost:
                break
            damping *= 10
        else:
            return T
        converged = cost - candidate_cost <= 1e-6 * cost or np.abs(steps).max() < 1e-9
        T, cost, damping = candidate, candidate_cost, max(damping / 10, 1e-12)
        if converged:
            break
    return T


def refine_pose(K: np.ndarray, T_camera_world: np.ndarray, points_world: np.ndarray, pixels: np.ndarray,
                sigmas: np.ndarray | None = None, *, huber_px: float = HUBER_PX, rounds: int = 2,
                max_iterations: int = 10) -> PoseRefinement:
    """Refine one camera pose against fixed points: (N, 3) ``points_world`` seen at (N, 2) undistorted
    ``pixels`` with (N,) ``sigmas`` (px, None for all 1) under the pinhole ``K``, from the start
    ``T_camera_world`` (4, 4).

    Minimises the module's robust cost (Huber at ``huber_px`` on the whitened error). Each of
    ``rounds`` runs up to ``max_iterations`` Levenberg-Marquardt iterations on the observations then
    classed inliers (all, at first), and classes them afresh by the chi-square test; dropping the
    outliers after the first round removes the pull they keep under Huber's bounded influence (as
    ORB-SLAM's pose optimisation does). pycolmap's ``refine_absolute_pose`` was measured against this
    (docs/slam.md): a Cauchy loss without per-observation sigmas, and slower per point. Points behind
    the camera are outliers; with fewer than three observations to refine on, the pose stays as it
    is. Raises ValueError on malformed inputs or fewer than 3 points.
    """
    K = _check_K(K)
    T = check_transform(T_camera_world, "T_camera_world")
    points = check_shape(points_world, "N,3", "points_world", np.float64)
    pixels = check_shape(pixels, f"{len(points)},2", "pixels", np.float64)
    if len(points) < 3 or not np.all(np.isfinite(points)):
        raise ValueError(f"points_world must be finite with N >= 3, got {len(points)} points")
    if not np.all(np.isfinite(pixels)):
        raise ValueError("pixels must be finite")
    sigmas = _check_sigmas(sigmas, len(points))
    if rounds < 1 or max_iterations < 1 or not huber_px > 0:
        raise ValueError(f"rounds and max_iterations must be >= 1 and huber_px > 0, got {rounds}, "
                         f"{max_iterations} and {huber_px}")
    errors = reprojection_errors(K, T, points, pixels)
    used = errors < np.inf
    for _ in range(rounds):
        if used.sum() < 3:
            break
        T = _refine_round(K, T, points[used], pixels[used], sigmas[used], huber_px, max_iterations)
        errors = reprojection_errors(K, T, points, pixels)
        used = (errors / sigmas) ** 2 <= CHI2_2DOF_95
    inliers = (errors / sigmas) ** 2 <= CHI2_2DOF_95
    return PoseRefinement(T, inliers, _rms(errors[inliers]))
