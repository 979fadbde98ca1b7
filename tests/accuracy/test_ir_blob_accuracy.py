"""IR blob centroids against the ground truth of the synthetic ``ir_rig`` scene (640x480, spheres of
8 mm at about 2.2 m, so blobs of about 2 px radius, with lens distortion).

Requirement: for isolated blobs (every other sphere's projection at least ``ISOLATION_PX`` away,
``EDGE_PX`` inside the image), RMS distance from the projected sphere centres below 0.05 px and
no flag; pairs of spheres whose projections overlap (``PAIR_RADII`` of the blob radius apart,
no third sphere near) give one blob that is flagged, MERGED once they are 1.5 radii apart.
"""

from __future__ import annotations

import numpy as np
import pytest

from services.detection.blobs.bright import BlobFlag, detect_ir_blobs
from services.geometry.camera import project_points
from services.geometry.se3 import invert, transform_points
from services.synthetic import make_scene

pytestmark = pytest.mark.slow

INDICES = range(0, 3000, 10)
ISOLATION_PX = 12.0
EDGE_PX = 6.0
PAIR_RADII = (0.7, 1.9)
MERGED_RADII = 1.5


def visible_spheres(scene, camera, index: int) -> tuple[np.ndarray, np.ndarray]:
    """(N, 2) projected centres (px) and (N,) blob radii (px) of the spheres ``camera`` sees in frame ``index``."""
    T_cam_world = invert(camera.T_rig_camera)
    hidden = scene.occlusions(index)
    pixels, radii = [], []
    for body, T_world_body in scene.body_poses(index).items():
        centres = transform_points(T_cam_world @ T_world_body, scene.bodies[body])
        for j, (pixel, depth) in enumerate(zip(project_points(centres, camera.K, camera.dist), centres[:, 2],
                                               strict=True)):
            if (camera.name, body, j) not in hidden:
                pixels.append(pixel)
                radii.append(camera.K[0, 0] * scene.sphere_radius / depth)
    return np.array(pixels), np.array(radii)


@pytest.fixture(scope="module")
def scored():
    """(isolated: [(distance px, flags)], pairs: [(separation in radii, flags, blobs near the pair, the two
    ``SPLIT`` rows a split adds left out)])."""
    scene = make_scene("ir_rig", body_count=4)
    isolated, pairs = [], []
    for index in INDICES:
        frame = scene.render(index)
        for camera in scene.cameras:
            blobs = detect_ir_blobs(frame.images[camera.name])
            pixels, radii = visible_spheres(scene, camera, index)
            inside = np.all((pixels > EDGE_PX) & (pixels < (camera.width - EDGE_PX, camera.height - EDGE_PX)), axis=1)
            gaps = np.linalg.norm(pixels[:, None] - pixels[None], axis=2) + np.diag(np.full(len(pixels), np.inf))
            for i in np.flatnonzero(inside):
                order = np.argsort(gaps[i])
                if gaps[i, order[0]] >= ISOLATION_PX:
                    distances = np.linalg.norm(blobs.centroids - pixels[i], axis=1)
                    k = int(np.argmin(distances))
                    isolated.append((distances[k], int(blobs.flags[k])))
                j = int(order[0])
                separation = gaps[i, j] / radii[[i, j]].mean()
                if i < j and inside[j] and PAIR_RADII[0] <= separation <= PAIR_RADII[1] \
                        and min(gaps[i, order[1]], np.delete(gaps[j], i).min()) >= ISOLATION_PX:
                    middle = (pixels[i] + pixels[j]) / 2
                    whole = blobs.select(~blobs.flagged(BlobFlag.SPLIT))
                    distances = np.linalg.norm(whole.centroids - middle, axis=1)
                    pairs.append((separation, int(whole.flags[np.argmin(distances)]),
                                  int(np.sum(distances < ISOLATION_PX / 2))))
    return isolated, pairs


def test_isolated_blob_centroids_sit_on_the_projected_sphere_centres(scored):
    isolated, _ = scored
    errors = np.array([distance for distance, _ in isolated])
    print(f"\n{len(errors)} isolated blobs: centroid error RMS {np.sqrt(np.mean(errors**2)):.3f} px, "
          f"max {errors.max():.3f} px")
    assert len(errors) > 1000
    assert np.sqrt(np.mean(errors**2)) < 0.05 and errors.max() < 0.15
    assert not any(flags for _, flags in isolated)


def test_overlapping_spheres_give_one_flagged_blob(scored):
    _, pairs = scored
    assert len(pairs) >= 10
    assert all(count == 1 and flags & (BlobFlag.MERGED | BlobFlag.OCCLUDED) for _, flags, count in pairs)
    apart = [flags for separation, flags, _ in pairs if separation >= MERGED_RADII]
    assert len(apart) >= 5 and all(flags & BlobFlag.MERGED for flags in apart)
