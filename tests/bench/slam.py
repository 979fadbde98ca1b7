"""SLAM optimisation speed and accuracy on synthetic problems (``tests.slam_problems``), one thread.

``bundle_adjust``: local bundle adjustments of 10 keyframes (two fixed) and 500 / 1000 / 2000 points,
and of 20 keyframes and 2000 points, with the defaults (at most 20 iterations, stop below a 1e-6
relative decrease), pyramid sigmas of four levels, 1 px noise per sigma, 10 % gross outliers, a start
1 deg / 5 cm off; ``DRAWS`` problems each: wall and CPU time p50 (the whole call: checks, building
pycolmap's reconstruction, Ceres, errors), iterations, largest pose error against the truth. CPU time
is the figure to trust on a shared machine; wall time is what a caller waits.

``refine_pose``: 300 and 1000 points of one keyframe (``tests.slam_problems.pose_problem``) refined
by ``refine_pose`` (two rounds), by pycolmap's ``refine_absolute_pose`` (Cauchy loss at the same
scale, every observation, no sigmas) and by four rounds of ``cv2.solvePnPRefineLM`` on the
observations inside the chi-square bound (all at first; it stops with fewer than three); ``DRAWS``
draws, each run through all three back to back: p50 CPU time, median rotation (deg) and camera-centre
(mm) error.
``python -m tests.bench.slam`` prints the lines.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from typing import Any

import cv2
import numpy as np
import pycolmap

from services.geometry.rotation import rotation_angle
from services.geometry.se3 import invert
from services.slam.optimisation import CHI2_2DOF_95, HUBER_PX, bundle_adjust, refine_pose, reprojection_errors
from tests.bench.blobs import one_opencv_thread
from tests.slam_problems import pose_problem, synthetic_problem

DRAWS = 7
BUNDLES = ((10, 500), (10, 1000), (10, 2000), (20, 2000))
POSE_POINTS = (300, 1000)

Refiner = Callable[[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray], np.ndarray]


def pose_error(T: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """Rotation (deg) and camera-centre (m) difference."""
    return (float(np.degrees(rotation_angle(T[:3, :3], truth[:3, :3]))),
            float(np.linalg.norm(invert(T)[:3, 3] - invert(truth)[:3, 3])))


def colmap_refiner(K: np.ndarray, start: np.ndarray, points: np.ndarray, pixels: np.ndarray,
                   sigmas: np.ndarray) -> np.ndarray:
    camera = pycolmap.Camera(camera_id=1, model="PINHOLE", width=640, height=480,
                             params=[K[0, 0], K[1, 1], K[0, 2], K[1, 2]])
    options = pycolmap.AbsolutePoseRefinementOptions()
    options.loss_function_scale = HUBER_PX
    refined = pycolmap.refine_absolute_pose(pycolmap.Rigid3d(start[:3]), pixels, points,
                                            np.ones(len(points), dtype=bool), camera, options)
    T = np.eye(4)
    T[:3] = refined["cam_from_world"].matrix()
    return T


def opencv_refiner(K: np.ndarray, start: np.ndarray, points: np.ndarray, pixels: np.ndarray,
                   sigmas: np.ndarray) -> np.ndarray:
    rvec, tvec = cv2.Rodrigues(start[:3, :3])[0], start[:3, 3:].copy()
    inliers = np.ones(len(points), dtype=bool)
    T = start
    for _ in range(4):
        if inliers.sum() < 3:
            break
        rvec, tvec = cv2.solvePnPRefineLM(points[inliers], pixels[inliers], K, None, rvec, tvec)
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = cv2.Rodrigues(rvec)[0], tvec.ravel()
        inliers = (reprojection_errors(K, T, points, pixels) / sigmas) ** 2 <= CHI2_2DOF_95
    return T


def ours(K: np.ndarray, start: np.ndarray, points: np.ndarray, pixels: np.ndarray, sigmas: np.ndarray) -> np.ndarray:
    return refine_pose(K, start, points, pixels, sigmas).T_camera_world


def bundle_lines() -> list[dict[str, Any]]:
    lines = []
    for keyframes, points in BUNDLES:
        times, cpu, iterations, angles, distances, rms = [], [], [], [], [], []
        for draw in range(DRAWS):
            sp = synthetic_problem(np.random.default_rng(draw), keyframes=keyframes, points=points, levels=4)
            started = time.process_time()
            result = bundle_adjust(sp.problem)
            cpu.append(time.process_time() - started)
            times.append(result.seconds)
            iterations.append(result.iterations)
            errors = [pose_error(result.poses[k], T) for k, T in sp.poses.items()]
            angles.append(max(a for a, _ in errors))
            distances.append(max(d for _, d in errors))
            rms.append(result.final_rms_px)
        lines.append({"bench": "slam", "variant": "bundle_adjust", "keyframes": keyframes, "points": points,
                      "observations": len(sp.problem.pixels), "draws": DRAWS,
                      "p50_ms": round(float(np.median(times)) * 1e3, 1),
                      "cpu_p50_ms": round(float(np.median(cpu)) * 1e3, 1),
                      "iterations_median": float(np.median(iterations)),
                      "max_rotation_error_deg_median": round(float(np.median(angles)), 4),
                      "max_centre_error_mm_median": round(float(np.median(distances)) * 1e3, 2),
                      "final_rms_px_median": round(float(np.median(rms)), 3)})
    return lines


def pose_lines() -> list[dict[str, Any]]:
    refiners: dict[str, Refiner] = {"refine_pose": ours, "pycolmap_refine_absolute_pose": colmap_refiner,
                                    "opencv_refine_lm_4_rounds": opencv_refiner}
    lines = []
    for count in POSE_POINTS:
        figures: dict[str, list[tuple[float, float, float]]] = {name: [] for name in refiners}
        for draw in range(DRAWS):
            K, truth, points, pixels, sigmas, _, start = pose_problem(draw, count)
            for name, refine in refiners.items():
                started = time.process_time()
                T = refine(K, start, points, pixels, sigmas)
                figures[name].append((time.process_time() - started, *pose_error(T, truth)))
        for name, values in figures.items():
            seconds, angles, distances = (np.array(column) for column in zip(*values, strict=True))
            lines.append({"bench": "slam", "variant": name, "points": count, "draws": DRAWS,
                          "cpu_p50_ms": round(float(np.median(seconds)) * 1e3, 2),
                          "rotation_error_deg_median": round(float(np.median(angles)), 4),
                          "centre_error_mm_median": round(float(np.median(distances)) * 1e3, 2)})
    return lines


def bench_slam() -> list[dict[str, Any]]:
    with one_opencv_thread():
        return bundle_lines() + pose_lines()


if __name__ == "__main__":
    for line in bench_slam():
        print(json.dumps(line), flush=True)
