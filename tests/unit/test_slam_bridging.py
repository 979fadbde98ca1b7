"""Bridging a frame from the last tracked one (``services.slam.bridging``), on a street a camera drives along.

The map's world is the street's frame scaled by ``MAP_SCALE`` (a monocular map's units are arbitrary); the
camera drives ``STEP_M`` forward between the two frames, turning a little. Matches are exact projections
with ``NOISE_PX`` of noise.
"""

import cv2
import numpy as np
import pytest

from services.geometry.camera import intrinsics, look_at, project_points
from services.geometry.rotation import matrix_from_rotvec, rotation_angle
from services.geometry.se3 import invert, make_transform, transform_points
from services.slam.bridging import MIN_SCALE_POINTS, bridge_pair
from services.slam.initialisation import InitialisationSettings

K = intrinsics(1226, 370, 82.0)
SIZE = (1226, 370)
MAP_SCALE = 0.03
STEP_M = 2.0
NOISE_PX = 0.5
SETTINGS = InitialisationSettings(min_parallax_deg=0.4)


def street(seed: int) -> np.ndarray:
    """(M, 3) points of two facades and a road, metres, x along the street, z up."""
    rng = np.random.default_rng(seed)
    along = rng.uniform(4.0, 60.0, 1200)
    side = rng.choice([-6.0, 6.0], 1200) + rng.normal(0.0, 0.5, 1200)
    height = rng.uniform(-1.6, 6.0, 1200)
    road = height < -1.2
    side[road] = rng.uniform(-5.0, 5.0, road.sum())
    height[road] = -1.6
    return np.column_stack([along, side, height])


def camera_at(x: float, yaw_deg: float) -> np.ndarray:
    """(4, 4) ``T_camera_street`` of a camera at 0 m height, ``x`` along the street, turned ``yaw_deg``."""
    yaw = np.radians(yaw_deg)
    eye = np.array([x, 0.0, 0.0])
    return invert(look_at(eye, eye + np.array([np.cos(yaw), np.sin(yaw), 0.0]), np.array([0.0, 0.0, 1.0])))


def to_map(T_camera_street: np.ndarray) -> np.ndarray:
    """The same camera pose in the map's units (camera from map)."""
    return make_transform(T_camera_street[:3, :3], T_camera_street[:3, 3] * MAP_SCALE)


def observe(points: np.ndarray, T_last: np.ndarray, T_new: np.ndarray, seed: int) -> tuple[np.ndarray, ...]:
    """``(pixels_last, pixels_new, points seen by both)``: (N, 2), (N, 2), (N, 3) street metres."""
    rng = np.random.default_rng(seed)
    pixels, fronts = [], []
    for T in (T_last, T_new):
        in_camera = transform_points(T, points)
        front = in_camera[:, 2] > 1.0
        projected = project_points(np.where(front[:, None], in_camera, 1.0), K)
        fronts.append(front & np.all((projected >= 0) & (projected < SIZE), axis=1))
        pixels.append(projected)
    seen = fronts[0] & fronts[1]
    return (*(p[seen] + rng.normal(0.0, NOISE_PX, (seen.sum(), 2)) for p in pixels), points[seen])


def errors(T_estimated: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    """(rotation error, deg; camera centre error as a fraction of ``STEP_M``)."""
    rotation = np.degrees(rotation_angle(T_estimated[:3, :3], T_true[:3, :3]))
    centre = np.linalg.norm(invert(T_estimated)[:3, 3] - invert(T_true)[:3, 3]) / (STEP_M * MAP_SCALE)
    return float(rotation), float(centre)


@pytest.mark.parametrize("seed", range(4))
def test_the_maps_points_set_the_scale_and_the_pose_matches_pnp_on_them(seed):
    T_last, T_new = camera_at(10.0, 3.0), camera_at(10.0 + STEP_M, -2.0)
    last_pixels, new_pixels, seen = observe(street(seed), T_last, T_new, seed)
    map_points = np.full((len(seen), 3), np.nan)
    known = np.random.default_rng(seed).random(len(seen)) < 0.2
    map_points[known] = seen[known] * MAP_SCALE
    assert known.sum() >= MIN_SCALE_POINTS
    bridge = bridge_pair(K, to_map(T_last), last_pixels, new_pixels, map_points, 123.0, SETTINGS)
    assert bridge is not None and bridge.from_map
    rotation, centre = errors(bridge.T_camera_world, to_map(T_new))
    assert rotation < 0.1 and centre < 0.03, (rotation, centre)
    ok, rvec, tvec = cv2.solvePnP(map_points[known], new_pixels[known], K, None, flags=cv2.SOLVEPNP_SQPNP)
    assert ok
    pnp = make_transform(matrix_from_rotvec(rvec.ravel()), tvec.ravel())
    rotation, centre = errors(bridge.T_camera_world, pnp)
    assert rotation < 0.1 and centre < 0.03, (rotation, centre)
    made = bridge.inliers
    assert made.mean() > 0.8
    depth_errors = np.linalg.norm(bridge.points_world[made] - seen[made] * MAP_SCALE, axis=1)
    distances = np.linalg.norm(transform_points(to_map(T_last), seen[made] * MAP_SCALE), axis=1)
    assert np.median(depth_errors / distances) < 0.05


@pytest.mark.parametrize("seed", range(4))
def test_without_map_points_the_predicted_distance_sets_the_scale(seed):
    T_last, T_new = camera_at(20.0, 0.0), camera_at(20.0 + STEP_M, 4.0)
    last_pixels, new_pixels, _ = observe(street(seed), T_last, T_new, seed)
    no_points = np.full((len(last_pixels), 3), np.nan)
    true_distance = STEP_M * MAP_SCALE
    bridge = bridge_pair(K, to_map(T_last), last_pixels, new_pixels, no_points, true_distance, SETTINGS)
    assert bridge is not None and not bridge.from_map
    rotation, centre = errors(bridge.T_camera_world, to_map(T_new))
    assert rotation < 0.1 and centre < 0.03, (rotation, centre)
    longer = bridge_pair(K, to_map(T_last), last_pixels, new_pixels, no_points, 1.5 * true_distance, SETTINGS)
    assert longer is not None
    step = np.linalg.norm((longer.T_camera_world @ invert(to_map(T_last)))[:3, 3])
    assert step == pytest.approx(1.5 * true_distance, rel=1e-6)


def test_a_turn_on_the_spot_is_not_bridged():
    T_last, T_new = camera_at(10.0, 0.0), camera_at(10.0, 3.0)
    last_pixels, new_pixels, seen = observe(street(0), T_last, T_new, 0)
    bridge = bridge_pair(K, to_map(T_last), last_pixels, new_pixels, seen * MAP_SCALE, 0.05, SETTINGS)
    assert bridge is None


def test_map_points_whose_depths_disagree_with_the_pairs_give_no_bridge():
    """Map points a third nearer or further at random (a map gone wrong there, or a pair whose depths are
    that uncertain): their depth ratios spread beyond ``MAX_SCALE_SPREAD``, and nothing is bridged."""
    T_last, T_new = camera_at(10.0, 3.0), camera_at(10.0 + STEP_M, -2.0)
    last_pixels, new_pixels, seen = observe(street(0), T_last, T_new, 0)
    rng = np.random.default_rng(0)
    camera_points = transform_points(T_last, seen) * rng.choice([2 / 3, 1.0, 4 / 3], (len(seen), 1))
    map_points = transform_points(invert(T_last), camera_points) * MAP_SCALE
    assert bridge_pair(K, to_map(T_last), last_pixels, new_pixels, map_points, 123.0, SETTINGS) is None
    kept = bridge_pair(K, to_map(T_last), last_pixels, new_pixels, seen * MAP_SCALE, 123.0, SETTINGS)
    assert kept is not None and kept.from_map
