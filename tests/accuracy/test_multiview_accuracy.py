"""Blob correspondences and triangulation against the ``ir_rig`` scene's ground truth.

Blobs are the exact projections of the true sphere centres (through each camera's distortion)
plus Gaussian noise of 0.05 px per axis; a sphere's blob centroid is not exactly its centre's
projection, which these tests leave aside. The rig: 1280x1024 cameras, 1 m apart, bodies
about 2 m away. Every triangulated point is scored by which blobs it was made from (all of one
sphere, or not) and by its distance to that sphere's true centre.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pytest

from services.estimation.bodies.correspondence import CorrespondenceOptions, triangulate_blobs
from services.geometry.se3 import transform_points
from services.geometry.triangulation import reproject
from services.synthetic import make_scene

pytestmark = pytest.mark.slow

SIGMA_PX = 0.05
FRAMES = range(0, 600, 10)
SIZE = (1280, 1024)
GHOSTS = 5
"""Spurious blobs per camera and frame, uniform over the image."""


@dataclass
class Score:
    spheres: int = 0
    found: int = 0
    mixed: int = 0
    phantoms: int = 0
    errors_m: list[float] = field(default_factory=list)


def run(count: int, ghosts: int = 0, hide: bool = False, options: CorrespondenceOptions | None = None,
        seed: int = 0) -> Score:
    """Score of ``triangulate_blobs`` over FRAMES with ``count`` cameras; ``hide``: one sphere per
    frame loses its blob in one camera."""
    scene = make_scene("ir_rig", camera_count=count, width=SIZE[0], height=SIZE[1], baseline=1.0)
    options = options or CorrespondenceOptions(sigma_px=SIGMA_PX)
    rng = np.random.default_rng(seed)
    score = Score()
    for index in FRAMES:
        truth = np.concatenate([transform_points(T, scene.bodies[name]) for name, T in scene.body_poses(index).items()])
        hidden = (int(rng.integers(count)), int(rng.integers(len(truth)))) if hide else None
        blobs, owners = [], []
        for c, camera in enumerate(scene.cameras):
            pixels = reproject(camera, truth) + rng.normal(0.0, SIGMA_PX, (len(truth), 2))
            owner = np.arange(len(truth))
            if hidden is not None and hidden[0] == c:
                pixels, owner = np.delete(pixels, hidden[1], axis=0), np.delete(owner, hidden[1])
            order = rng.permutation(len(pixels) + ghosts)
            pixels = np.vstack([pixels, rng.uniform((0, 0), SIZE, (ghosts, 2))])[order]
            blobs.append(pixels)
            owners.append(np.concatenate([owner, np.full(ghosts, -1)])[order])
        score.spheres += len(truth)
        for point in triangulate_blobs(scene.cameras, blobs, options):
            made_of = {int(owners[c][i]) for c, i in zip(point.camera_indices, point.blob_indices, strict=True)}
            if made_of == {-1}:
                score.phantoms += 1
            elif len(made_of) > 1 or -1 in made_of:
                score.mixed += 1
            else:
                score.found += 1
                score.errors_m.append(float(np.linalg.norm(point.point - truth[made_of.pop()])))
    return score


@pytest.mark.parametrize("count", [2, 3])
def test_sphere_centres_within_a_fraction_of_a_millimetre(count):
    score = run(count)
    print(f"\n{count} cameras: {score.found} of {score.spheres} spheres triangulated, median error "
          f"{np.median(score.errors_m) * 1e3:.2f} mm, {score.mixed} from blobs of two spheres")
    assert score.mixed == 0
    assert score.found >= (0.95 if count == 2 else 1.0) * score.spheres
    assert np.median(score.errors_m) < 0.3e-3


@pytest.mark.parametrize("count", [2, 3])
def test_ghost_blobs_make_no_point_of_wrong_correspondences(count):
    score = run(count, ghosts=GHOSTS)
    assert score.mixed == 0
    assert score.found >= (0.95 if count == 2 else 1.0) * score.spheres
    assert np.median(score.errors_m) < 0.3e-3


def test_three_views_required_leave_no_phantom():
    score = run(3, ghosts=GHOSTS, options=CorrespondenceOptions(sigma_px=SIGMA_PX, min_views=3))
    assert score.mixed == 0 and score.phantoms == 0
    assert score.found >= 0.99 * score.spheres


def test_sphere_hidden_from_one_of_three_cameras_is_still_triangulated():
    score = run(3, hide=True)
    assert score.mixed == 0 and score.found == score.spheres
    assert np.median(score.errors_m) < 0.3e-3
