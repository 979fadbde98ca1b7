"""Wand calibration against the ``ir_rig`` scene's true extrinsics, 2 and 3 cameras.

Blobs are the exact projections of the wand's sphere centres plus Gaussian noise of ``SIGMA_PX``
per axis (the scene's rendered blob centroids are within about 0.1 px of them), 300 frames a
sixth of a second apart; the scene's occlusions and the image border drop spheres now and then.
Both the estimate and the truth are expressed in the first camera's frame.
"""

from __future__ import annotations

import numpy as np
import pytest

from services.calibration.wand import Wand, calibrate_wand
from tests.wand_blobs import extrinsic_errors, wand_blobs, wand_scene

pytestmark = pytest.mark.slow

SIGMA_PX = 0.1
FRAMES = range(0, 1500, 5)


@pytest.mark.parametrize("count", [2, 3])
def test_extrinsics_within_a_millimetre_and_a_twentieth_of_a_degree(count):
    scene = wand_scene(count)
    wand = Wand(np.array(scene.options.wand_spheres))
    result = calibrate_wand(scene.cameras, wand_blobs(scene, FRAMES, SIGMA_PX), wand)
    position_mm, rotation_deg = extrinsic_errors(scene, result.T_rig_camera)
    print(f"wand {count} cameras: position error max {position_mm.max():.3f} mm, rotation error max "
          f"{rotation_deg.max():.4f} deg, length error {result.length_error_mean_mm:+.3f} "
          f"+- {result.length_error_std_mm:.3f} mm, reprojection RMS {result.rms_px:.3f} px, "
          f"frames used {result.frames_used} skipped {result.frames_skipped} {result.skipped}")
    assert position_mm.max() < 1.0 and rotation_deg.max() < 0.05
    assert abs(result.length_error_mean_mm) < 1.0 and result.length_error_std_mm < 10.0
    assert result.rms_px < 2 * SIGMA_PX
    assert result.frames_used > 0.7 * len(FRAMES) and result.frames_used + result.frames_skipped == len(FRAMES)
    assert result.rejected == 0


def test_false_wands_are_rejected_by_the_adjustment():
    """Five frames of camera 1 replaced by a collinear triple elsewhere in the image: identified as the wand,
    then dropped as outliers; the extrinsics stay as accurate."""
    scene = wand_scene(3)
    wand = Wand(np.array(scene.options.wand_spheres))
    blobs = wand_blobs(scene, FRAMES, SIGMA_PX)
    fakes = [10, 60, 110, 160, 210]
    for f in fakes:
        blobs[f][1] = np.array([[100.0, 100.0], [130.0 + f / 10, 118.0], [200.0, 160.0 + f / 10]])
        blobs[f][1][1] = blobs[f][1][0] + 0.3 * (blobs[f][1][2] - blobs[f][1][0])
    result = calibrate_wand(scene.cameras, blobs, wand)
    position_mm, rotation_deg = extrinsic_errors(scene, result.T_rig_camera)
    assert result.rejected == len(fakes)
    assert position_mm.max() < 1.0 and rotation_deg.max() < 0.05
