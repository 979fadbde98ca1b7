"""The loss analysis's classification (``tests/accuracy/stereo_losses.py``): a lost frame's cause and the tracker's
step where it was lost, on hand-made discs, blobs and points of the hard scene's first frame."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from services.estimation.bodies.labelled import Found
from services.estimation.bodies.rigid import Matching, MatchOptions
from services.geometry.camera_stack import CameraStack
from services.geometry.triangulation import TriangulatedPoint
from tests.accuracy.stereo_losses import Discs, cause, hard_scene, stage

MATCH = MatchOptions()


@pytest.fixture(scope="module")
def scene():
    return hard_scene()


@pytest.fixture(scope="module")
def discs(scene):
    """The hard scene's frame 0, the strays put out of the way (far from every sphere, in every image)."""
    found = Discs.of(scene, CameraStack.of(list(scene.cameras)), 0)
    strays = found.owner == ""
    pixels = found.pixels.copy()
    pixels[strays] = -1000.0
    world = found.world.copy()
    world[strays] = 100.0
    return dataclasses.replace(found, pixels=pixels, world=world)


def index_where(scene, hidden_body: str | None) -> int:
    """A frame whose occlusions hide a sphere of ``hidden_body`` (None: hide nothing)."""
    return next(i for i in range(0, 6000, 30) if {body for _, body, _ in scene.occlusions(i)} == (
        set() if hidden_body is None else {hidden_body}))


def head(discs) -> np.ndarray:
    return np.flatnonzero(discs.owner == "head")


def moved(discs, disc: int, pixel: tuple[float, float], camera: int = 0):
    pixels = discs.pixels.copy()
    pixels[disc, camera] = pixel
    return dataclasses.replace(discs, pixels=pixels)


def test_the_first_frame_is_clean(scene, discs):
    assert discs.lit[discs.owner != ""].all()
    assert cause(scene, discs, "head", index_where(scene, None)) in ("unknown", "edge")


def test_causes_in_their_order(scene, discs):
    a, b = head(discs)[:2]
    clear, hiding = index_where(scene, None), index_where(scene, "head")
    near = discs.pixels[a, 0] + (discs.radii[a, 0] + discs.radii[b, 0] + 1.0, 0.0)
    merged = moved(discs, b, tuple(near))
    assert cause(scene, merged, "head", clear) == "merged"
    assert cause(scene, merged, "head", hiding) == "merged"
    assert cause(scene, discs, "head", hiding) == "hidden"
    stray = int(np.flatnonzero(discs.owner == "")[0])
    beside = moved(discs, stray, tuple(discs.pixels[a, 0] + (6.0, 0.0)))
    beside = dataclasses.replace(beside, lit=beside.lit | (beside.owner == "")[:, None])
    assert cause(scene, beside, "head", clear) == "stray"
    assert cause(scene, beside, "tool", clear) != "stray"
    edge = moved(discs, a, (4.0, 200.0))
    assert cause(scene, edge, "head", clear) == "edge"
    assert cause(scene, edge, "tool", clear) != "edge"


def exact_blobs(discs) -> list[np.ndarray]:
    """Per camera, a blob at every lit disc's image, in disc order."""
    return [discs.pixels[discs.lit[:, c], c] for c in range(discs.lit.shape[1])]


def blob_of(discs, disc: int, camera: int) -> int:
    return int(np.count_nonzero(discs.lit[:disc, camera]))


def found_with(discs, points: list[tuple[np.ndarray, tuple[int, int], tuple[int, int]]]) -> Found:
    """A set's ``Found`` of ``(point, cameras, blob indices)``, no body found."""
    made = [TriangulatedPoint(p, 0.1, np.eye(3) * 1e-8, cameras, blobs) for p, cameras, blobs in points]
    world = np.array([p for p, _, _ in points]).reshape(-1, 3)
    return Found(made, world, np.zeros((len(made), 3, 3)), Matching())


def sphere_points(discs, spheres) -> list[tuple[np.ndarray, tuple[int, int], tuple[int, int]]]:
    return [(discs.world[d], (0, 1), (blob_of(discs, d, 0), blob_of(discs, d, 1))) for d in spheres]


def test_steps_in_their_order(scene, discs):
    spheres = head(discs)
    blobs = exact_blobs(discs)
    all_labelled = np.zeros((len(spheres), 3), np.int64)
    three, four = sphere_points(discs, spheres[:3]), sphere_points(discs, spheres[:4])
    assert stage(scene, discs, "head", blobs, None, found_with(discs, four), MATCH) == "matching"
    assert stage(scene, discs, "head", blobs, None, found_with(discs, three), MATCH) == "search"
    assert stage(scene, discs, "head", blobs, all_labelled, found_with(discs, three), MATCH) == "matching"
    shifted = [(p + (0.0, 0.002, 0.0) if k == 0 else p, c, i) for k, (p, c, i) in enumerate(four)]
    assert stage(scene, discs, "head", blobs, None, found_with(discs, shifted), MATCH) == "matching"
    tight = MatchOptions(gate_rms=0.00025)
    assert stage(scene, discs, "head", blobs, None, found_with(discs, shifted), tight) == "residual"
    two = sphere_points(discs, spheres[:2])
    assert stage(scene, discs, "head", blobs, None, found_with(discs, two), MATCH) == "points"
    ghost = (discs.world[spheres[2]] + (0.06, 0.0, 0.0), (0, 1),
             (blob_of(discs, spheres[2], 0), blob_of(discs, spheres[3], 1)))
    assert stage(scene, discs, "head", blobs, None, found_with(discs, [*two, ghost]), MATCH) == "pairing"
    few_labels = np.full((len(spheres), 3), -1, np.int64)
    few_labels[:2] = 0
    assert stage(scene, discs, "head", blobs, few_labels, found_with(discs, two), MATCH) == "labels"
    without_head = [b if c == 0 else discs.pixels[discs.lit[:, c] & (discs.owner != "head"), c]
                    for c, b in enumerate(blobs)]
    assert stage(scene, discs, "head", without_head, None, found_with(discs, four), MATCH) == "blobs"
