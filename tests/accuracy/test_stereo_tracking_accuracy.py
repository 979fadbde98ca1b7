"""The stereo tracker on rendered frames of the ``ir_rig`` scene, scored against its truth.

Frames are rendered (640x480, the scene's default size and lens distortion, 8 mm spheres 1.85 to
2.55 m in front of the bar), their blobs found as the ``blobs`` node finds them, then put through
what the ``rigid_bodies`` node does per joined set (``tests.ir_tracking``). Requirements:

* three cameras 0.8 m apart: body position error median <= 0.5 mm, rotation median <= 0.2 deg;
* a sphere hidden from one camera in every half-second window: no pose off its body by more than
  ``GHOST_MM`` / ``GHOST_DEG`` (2 and 3 cameras; with 2 cameras and the former ``gate_rms`` of 2 mm, the
  wand was posed once on two of its spheres and another body's, a 1.3 mm fit 94 mm and 179 deg off);
* with 3 cameras, a body of four or more spheres with one of them hidden from one camera is posed
  in every frame where it is posed without the occlusion, within the accuracy bound (with 2
  cameras the share kept is measured);
* the default two-camera bar: the published covariance is honest, the position errors whitened by
  it have a root mean square within [0.7, 1.3] along each principal axis, with the node's default
  ``sigma_px`` (``auto``: the centroid noise estimated from the points' residuals) as with the detector's
  measured centroid error;
* a rig calibrated with the wand from rendered wand frames tracks within 1.5 times the position
  error median of the true rig, on the same frames.

``python -m tests.accuracy.test_stereo_tracking_accuracy`` prints the figures as JSON lines.
"""

from __future__ import annotations

import dataclasses
import json
from functools import cache
from typing import Any

import numpy as np
import pytest

from protocol.detections import Blobs
from services.calibration.wand import Wand, calibrate_wand
from services.estimation.bodies.node import Params, pixels
from services.geometry.se3 import invert
from services.synthetic import make_scene
from services.synthetic.ir_rig import LAYOUTS, IrRigScene
from tests.ir_tracking import Tracked, mean_mahalanobis, rendered_blobs, summary, track, whitened_rms
from tests.wand_blobs import extrinsic_errors

pytestmark = pytest.mark.slow

FRAMES = range(0, 3000, 25)
"""120 frames 0.83 s apart: 100 s of the scene's motion, 200 occlusion windows of which 120 are seen."""
WAND_FRAMES = range(0, 1000, 5)
WIDE = {"camera_count": 3, "baseline": 0.8}
GHOST_MM, GHOST_DEG = 2.0, 3.0
HONEST_SIGMA_PX = 0.012
"""Centroid error per axis of the blob detector on the scene's noiseless images (its 0.017 px RMS
distance over sqrt(2), tests/accuracy/test_ir_blob_accuracy.py)."""
DEFAULT_SIGMA_PX, DEFAULT_GATE_RMS = Params().correspondence.sigma_px, Params().match.gate_rms


@cache
def rendered(camera_count: int = 2, baseline: float = 0.3, occlusion_rate: float = 0.25,
             body_count: int = 3) -> tuple[IrRigScene, list[list[Blobs]]]:
    """The scene with these options and the blobs of its ``FRAMES``."""
    scene = make_scene("ir_rig", camera_count=camera_count, baseline=baseline, occlusion_rate=occlusion_rate,
                       body_count=body_count)
    assert isinstance(scene, IrRigScene)
    return scene, rendered_blobs(scene, FRAMES)


@cache
def tracked(camera_count: int = 2, baseline: float = 0.3, occlusion_rate: float = 0.25, body_count: int = 3,
            sigma_px: float | str = DEFAULT_SIGMA_PX, gate_rms: float = DEFAULT_GATE_RMS) -> list[Tracked]:
    """The poses of ``rendered``'s frames with the true rig and the node's ``sigma_px`` and ``gate_rms``."""
    scene, blobs = rendered(camera_count, baseline, occlusion_rate, body_count)
    params = Params(cameras=tuple(c.name for c in scene.cameras), sigma_px=sigma_px, gate_rms=gate_rms)
    return track(scene, FRAMES, blobs, params=params)


def wide_figures() -> dict[str, float | int]:
    poses = tracked(**WIDE, body_count=len(LAYOUTS))
    return {"frames": len(FRAMES), "bodies": len(LAYOUTS), **summary(poses)}


def ghost_figures(camera_count: int, gate_rms: float = DEFAULT_GATE_RMS) -> dict[str, Any]:
    """Every pose of the scene with a sphere hidden in every window, ``gate_rms`` the node's (m): how many are
    off their body by more than ``GHOST_MM`` or ``GHOST_DEG`` (ghosts)."""
    poses = tracked(camera_count, 0.8 if camera_count == 3 else 0.3, 1.0, len(LAYOUTS), gate_rms=gate_rms)
    ghosts = [t for t in poses if t.position_mm > GHOST_MM or t.rotation_deg > GHOST_DEG]
    return {"cameras": camera_count, "gate_rms_mm": 1000.0 * gate_rms, "poses": len(poses),
            "position_mm_max": max(t.position_mm for t in poses),
            "rotation_deg_max": max(t.rotation_deg for t in poses),
            "ghosts": len(ghosts), "ghost_frames": [f"{t.index}:{t.body}" for t in ghosts]}


def hidden_sphere_figures(camera_count: int) -> dict[str, float | int]:
    """Frames where the scene hides one sphere of a 4+-sphere body from one camera and the body is posed with
    all its spheres without the occlusion (the same frame of the scene with ``occlusion_rate=0``; a frame where
    another sphere of the body is lost too, its blobs merged, is not one): how many keep a pose, with how many
    spheres, and their errors."""
    baseline = 0.8 if camera_count == 3 else 0.3
    scene, _ = rendered(camera_count, baseline, 1.0, len(LAYOUTS))
    occluded = {(t.index, t.body): t for t in tracked(camera_count, baseline, 1.0, len(LAYOUTS))}
    clear = {(t.index, t.body) for t in tracked(camera_count, baseline, 0.0, len(LAYOUTS))
             if t.spheres == len(scene.bodies[t.body])}
    cases = [(index, body) for index in FRAMES for _, body, _ in scene.occlusions(index)
             if len(scene.bodies[body]) >= 4 and (index, body) in clear]
    kept = [occluded[case] for case in cases if case in occluded]
    full = sum(t.spheres == len(scene.bodies[t.body]) for t in kept)
    return {"cameras": camera_count, "cases": len(cases), "posed": len(kept), "all_spheres": full,
            "one_sphere_missing": len(kept) - full, **summary(kept)}


def covariance_figures(sigma_px: float | str) -> dict[str, Any]:
    poses = tracked(sigma_px=sigma_px)
    spread = whitened_rms(poses)
    return {"cameras": 2, "sigma_px": sigma_px, **summary(poses), "whitened_rms": [round(float(s), 3) for s in spread],
            "mahalanobis2_mean": mean_mahalanobis(poses)}


@cache
def wand_figures() -> dict[str, float | int]:
    """The default bar calibrated from rendered wand frames (blobs without flags), then tracking the default
    scene's frames with it; the truth is put in the calibrated rig's frame (the first camera's)."""
    wand_scene = make_scene("ir_rig", motion="wand")
    assert isinstance(wand_scene, IrRigScene)
    blobs = [[pixels(b, flagged=False) for b in frame] for frame in rendered_blobs(wand_scene, WAND_FRAMES)]
    result = calibrate_wand(wand_scene.cameras, blobs, Wand(np.array(wand_scene.options.wand_spheres)))
    position_mm, rotation_deg = extrinsic_errors(wand_scene, result.T_rig_camera)
    scene, frames = rendered()
    assert [c.K.tolist() for c in scene.cameras] == [c.K.tolist() for c in wand_scene.cameras]
    calibrated = [dataclasses.replace(c, T_rig_camera=T) for c, T in zip(scene.cameras, result.T_rig_camera,
                                                                         strict=True)]
    poses = track(scene, FRAMES, frames, cameras=calibrated, T_frame_world=invert(scene.cameras[0].T_rig_camera))
    true_rig = summary(tracked())
    wand_rig = summary(poses)
    return {"wand_frames_used": result.frames_used, "extrinsics_mm_max": float(position_mm.max()),
            "extrinsics_deg_max": float(rotation_deg.max()), "reprojection_rms_px": result.rms_px,
            "true_rig_poses": true_rig["poses"], "true_rig_position_mm_median": true_rig["position_mm_median"],
            "wand_rig_poses": wand_rig["poses"], "wand_rig_position_mm_median": wand_rig["position_mm_median"],
            "wand_rig_position_mm_p90": wand_rig["position_mm_p90"],
            "wand_rig_rotation_deg_median": wand_rig["rotation_deg_median"]}


def test_three_cameras_wide_apart_pose_bodies_within_half_a_millimetre_and_a_fifth_of_a_degree():
    figures = wide_figures()
    print(figures)
    assert figures["poses"] >= 0.8 * len(FRAMES) * len(LAYOUTS)
    assert figures["position_mm_median"] <= 0.5 and figures["rotation_deg_median"] <= 0.2


@pytest.mark.parametrize("camera_count", [2, 3])
def test_no_ghost_body_with_occlusions(camera_count):
    figures = ghost_figures(camera_count)
    print(figures)
    assert figures["poses"] >= 0.6 * len(FRAMES) * len(LAYOUTS)
    assert figures["ghosts"] == 0


def test_a_body_with_a_sphere_hidden_from_one_of_three_cameras_keeps_tracking():
    figures = hidden_sphere_figures(3)
    print(figures)
    assert figures["cases"] >= 50
    assert figures["posed"] == figures["cases"]
    assert figures["position_mm_median"] <= 0.5 and figures["rotation_deg_median"] <= 0.2
    assert figures["position_mm_max"] <= GHOST_MM


def test_with_two_cameras_a_body_with_a_sphere_hidden_from_one_camera_is_posed_with_the_others():
    figures = hidden_sphere_figures(2)
    print(figures)
    assert figures["cases"] >= 50
    assert figures["posed"] >= 0.5 * figures["cases"] and figures["all_spheres"] == 0
    assert figures["position_mm_median"] <= 0.5 and figures["position_mm_max"] <= GHOST_MM


def honest(figures: dict) -> bool:
    return all(0.7 <= s <= 1.3 for s in figures["whitened_rms"])


def test_the_default_bar_publishes_an_honest_covariance():
    figures = covariance_figures(DEFAULT_SIGMA_PX)
    print(figures)
    assert DEFAULT_SIGMA_PX == "auto"
    assert honest(figures)


def test_the_covariance_is_honest_with_sigma_px_set_to_the_centroid_error():
    figures = covariance_figures(HONEST_SIGMA_PX)
    print(figures)
    assert figures["poses"] >= 0.6 * len(FRAMES) * 3
    assert honest(figures)
    assert 0.7**2 * 3 <= figures["mahalanobis2_mean"] <= 1.3**2 * 3


def test_a_wand_calibrated_rig_tracks_within_one_and_a_half_times_the_true_rigs_error():
    figures = wand_figures()
    print(figures)
    assert figures["wand_rig_poses"] >= 0.95 * figures["true_rig_poses"]
    assert figures["wand_rig_position_mm_median"] <= 1.5 * figures["true_rig_position_mm_median"]


if __name__ == "__main__":
    print(json.dumps({"test": "stereo_wide", **wide_figures()}))
    for count in (2, 3):
        print(json.dumps({"test": "stereo_ghosts", **ghost_figures(count)}))
        print(json.dumps({"test": "stereo_ghosts", **ghost_figures(count, gate_rms=0.002)}))
        print(json.dumps({"test": "stereo_hidden_sphere", **hidden_sphere_figures(count)}))
    for sigma in (DEFAULT_SIGMA_PX, HONEST_SIGMA_PX):
        print(json.dumps({"test": "stereo_covariance", **covariance_figures(sigma)}))
    print(json.dumps({"test": "stereo_wand_rig", **wand_figures()}))
