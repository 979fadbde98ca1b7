"""Wand calibration: the wand's blobs are told apart and ordered, frames that do not show it are skipped and
counted, the floor frame follows three points."""

import numpy as np
import pytest
from scipy.optimize import approx_fprime

from services.calibration.camera_info import CalibrationError
from services.calibration.wand import (
    SKIP_REASONS,
    Wand,
    WandAdjustment,
    calibrate_wand,
    floor_frame,
    identify_wand,
    order_lframe,
    reframe,
)
from services.geometry.camera import undistort_pixels
from services.geometry.rotation import matrix_from_rotvec
from tests.wand_blobs import wand_blobs, wand_scene

WAND = Wand(np.array([0.0, 0.15, 0.5]))


def line(start, end, ratio=0.3):
    start, end = np.asarray(start, float), np.asarray(end, float)
    return np.array([start, start + ratio * (end - start), end])


@pytest.mark.parametrize("permutation", [(0, 1, 2), (2, 1, 0), (1, 0, 2), (2, 0, 1)])
def test_blobs_are_ordered_first_end_middle_far_end(permutation):
    pixels = line((100, 50), (400, 300))
    order, reason = identify_wand(pixels[list(permutation)], WAND)
    assert reason == "" and order is not None
    assert np.allclose(pixels[list(permutation)][order], pixels)


def test_reversed_wand_is_ordered_from_its_first_end():
    pixels = line((400, 300), (100, 50))
    order, _ = identify_wand(pixels[::-1], WAND)
    assert order is not None and np.allclose(pixels[::-1][order], pixels)


@pytest.mark.parametrize(("pixels", "reason"), [
    (np.vstack([line((100, 50), (400, 300)), [[250, 400]]]), "blob_count"),
    (line((100, 50), (400, 300))[[0, 2]], "blob_count"),
    (np.zeros((0, 2)), "blob_count"),
    (line((100, 50), (400, 300)) + [[0, 0], [0, 4], [0, 0]], "not_collinear"),
    (line((100, 50), (110, 55)), "too_short"),
    (line((100, 50), (400, 300), ratio=0.45), "ambiguous_ends"),
])
def test_blobs_that_are_not_the_wand_are_refused_with_a_reason(pixels, reason):
    assert identify_wand(pixels, WAND) == (None, reason)
    assert reason in SKIP_REASONS


def test_a_wand_whose_ends_cannot_be_told_apart_is_refused():
    with pytest.raises(CalibrationError, match="off the wand's centre"):
        Wand(np.array([0.0, 0.26, 0.5]))
    with pytest.raises(CalibrationError, match="0 then increasing"):
        Wand(np.array([0.0, 0.5, 0.2]))


def test_frames_with_a_ghost_or_a_missing_blob_are_skipped_and_counted():
    scene = wand_scene(2, occlusion_rate=0.0)
    blobs = wand_blobs(scene, range(0, 400, 5), sigma_px=0.1)
    clean = calibrate_wand(scene.cameras, blobs, WAND)
    assert clean.frames_skipped == len(blobs) - clean.frames_used
    ghosts, missing = clean.frames[:5], clean.frames[5:12]
    for f in ghosts:
        blobs[f][0] = np.vstack([blobs[f][0], [[320.0, 240.0]]])
    for f in missing:
        blobs[f][1] = blobs[f][1][:2]
    result = calibrate_wand(scene.cameras, blobs, WAND)
    assert result.frames_used == clean.frames_used - 12
    assert result.frames_skipped == clean.frames_skipped + 12
    assert result.skipped["blob_count"] == clean.skipped.get("blob_count", 0) + 12
    assert not set(result.frames) & (set(ghosts) | set(missing))
    assert list(result.observations) == [clean.frames_used - 12] * 2


def test_adjustment_jacobian_matches_finite_differences():
    scene = wand_scene(3, occlusion_rate=0.0)
    blobs = wand_blobs(scene, range(0, 60, 5), sigma_px=0.5)
    observed = np.full((len(blobs), 3, 3, 2), np.nan)
    for f, frame in enumerate(blobs):
        for c, (camera, pixels) in enumerate(zip(scene.cameras, frame, strict=True)):
            order, _ = identify_wand(undistort_pixels(pixels, camera.K, camera.dist), WAND)
            if order is not None:
                observed[f, c] = pixels[order]
    seen = ~np.isnan(observed[..., 0, 0])
    keep = seen.sum(axis=1) >= 2
    T_camera_rig = np.array([np.linalg.inv(np.linalg.inv(scene.cameras[0].T_rig_camera) @ c.T_rig_camera)
                             for c in scene.cameras])
    problem = WandAdjustment(scene.cameras, observed[keep], seen[keep], WAND, T_camera_rig)
    x = problem.x0 + np.random.default_rng(2).normal(0.0, 0.01, len(problem.x0))
    analytic = problem.jacobian(x).toarray()
    numeric = approx_fprime(x, problem.residuals, 1e-7)
    assert analytic.shape == numeric.shape == (len(problem.residuals(x)), len(x))
    assert np.abs(analytic - numeric).max() < 1e-3 * np.abs(numeric).max()
    assert np.array_equal(analytic != 0, numeric != 0)


def test_too_few_wand_frames_is_one_clear_error():
    scene = wand_scene(2)
    blobs = [[np.zeros((2, 2)), np.zeros((3, 2))]] * 20
    with pytest.raises(CalibrationError, match="only 0 frames show the wand"):
        calibrate_wand(scene.cameras, blobs, WAND)
    with pytest.raises(CalibrationError, match="one blob list per camera"):
        calibrate_wand(scene.cameras, [[np.zeros((3, 2))]], WAND)


def test_floor_frame_from_three_points():
    rng = np.random.default_rng(3)
    R = matrix_from_rotvec(rng.normal(size=3))
    T_rig_floor = np.eye(4)
    T_rig_floor[:3, :3], T_rig_floor[:3, 3] = R, [0.3, 1.2, 2.5]
    local = np.array([[0.0, 0.0, 0.0], [0.5, 0.0, 0.0], [0.2, 0.4, 0.0]])
    points = local @ R.T + T_rig_floor[:3, 3]
    assert np.allclose(floor_frame(*points), T_rig_floor)
    cameras = np.array([np.eye(4), T_rig_floor])
    moved = reframe(cameras, T_rig_floor)
    assert np.allclose(moved[1], np.eye(4)) and np.allclose(moved[0], np.linalg.inv(T_rig_floor))
    with pytest.raises(CalibrationError, match="one line"):
        floor_frame(points[0], points[1], 2 * points[1] - points[0])


def test_lframe_spheres_are_ordered_corner_long_arm_short_arm():
    lframe = np.array([[1.0, 2.0, 3.0], [1.5, 2.0, 3.0], [1.0, 2.0, 3.35]])
    for permutation in ([0, 1, 2], [2, 0, 1], [1, 2, 0], [2, 1, 0]):
        assert np.array_equal(order_lframe(lframe[permutation]), lframe)
    with pytest.raises(CalibrationError, match="no right angle"):
        order_lframe(np.array([[0.0, 0.0, 0.0], [0.5, 0.0, 0.0], [0.2, 0.35, 0.0]]))
    with pytest.raises(CalibrationError, match="too alike"):
        order_lframe(np.array([[0.0, 0.0, 0.0], [0.5, 0.0, 0.0], [0.0, 0.48, 0.0]]))
