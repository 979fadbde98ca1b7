"""The compiled gating of ``labelled.label_blobs`` against the same rules written with NumPy over all spheres,
cameras and blobs at once: the same labels on scenes with strays, merged images, crowded cameras and spheres
behind a camera."""

import numpy as np
import pytest

from services.estimation.bodies.correspondence import gated_assignment, rig_geometry
from services.estimation.bodies.labelled import label_blobs
from services.geometry.camera_stack import CameraStack
from services.synthetic import make_scene


def numpy_labels(stack: CameraStack, blobs: list[np.ndarray], expected: np.ndarray, gate_px: float) -> np.ndarray:
    """The labelling rules as array operations: near within the gate, doubtful blobs and the spheres near them
    let go, each camera where a sphere keeps two blobs assigned, the others labelled pair by pair."""
    labels = np.full((len(expected), len(stack)), -1, np.int64)
    widest = max(len(b) for b in blobs)
    if not widest:
        return labels
    observed = np.full((len(stack), widest, 2), np.nan)
    for c, b in enumerate(blobs):
        observed[c, :len(b)] = b
    cost = np.linalg.norm(stack.project(expected)[:, :, None, :] - observed[None], axis=3)
    with np.errstate(invalid="ignore"):
        near = cost < gate_px
    doubtful = np.count_nonzero(near, axis=0) >= 2
    near &= ~np.any(near & doubtful[None], axis=2)[:, :, None]
    near &= ~doubtful[None]
    crowded = np.any(np.count_nonzero(near, axis=2) > 1, axis=0)
    spheres, cameras, columns = np.nonzero(near & ~crowded[None, :, None])
    labels[spheres, cameras] = columns
    for c in np.flatnonzero(crowded).tolist():
        for row, column in gated_assignment(np.where(near[:, c], cost[:, c], np.inf), gate_px):
            labels[row, c] = column
    return labels


@pytest.fixture(scope="module")
def stack() -> CameraStack:
    return rig_geometry(list(make_scene("ir_rig", camera_count=3).cameras)).stack


@pytest.mark.parametrize("seed", range(40))
def test_the_compiled_labels_are_the_array_versions(stack, seed):
    rng = np.random.default_rng(seed)
    expected = rng.uniform([-0.4, -0.4, 1.5], [0.4, 0.4, 2.5], (int(rng.integers(1, 12)), 3))
    if seed % 5 == 0:  # one sphere a metre behind camera 0
        centre = -stack.R_camera_world[0].T @ stack.t_camera_world[0]
        expected[0] = centre - stack.R_camera_world[0, 2]
        assert stack.depths(expected[:1])[0, 0] < 0
    projected = stack.project(expected)
    blobs = []
    for c in range(len(stack)):
        seen = projected[:, c][np.all(np.isfinite(projected[:, c]), axis=1)]
        kept = seen[rng.random(len(seen)) > 0.15]
        kept = kept + rng.normal(0.0, 0.8, kept.shape)
        doubled = min(len(kept), int(rng.integers(0, 3)))
        doubles = kept[:doubled] + rng.normal(0.0, 1.5, (doubled, 2))  # a second blob near a sphere
        strays = rng.uniform([0.0, 0.0], [640.0, 480.0], (int(rng.integers(0, 4)), 2))
        blobs.append(rng.permutation(np.concatenate([kept, doubles, strays])))
    gate = float(rng.choice([2.0, 3.0, 6.0, 25.0]))
    labels, images = label_blobs(stack, blobs, expected, gate)
    np.testing.assert_array_equal(labels, numpy_labels(stack, blobs, expected, gate))
    np.testing.assert_allclose(images, projected, rtol=0, atol=1e-9)  # NaN where behind a camera, as projected


def test_a_camera_without_blobs_labels_nothing_and_a_crowded_camera_is_assigned_pair_by_pair(stack):
    expected = np.array([[0.0, 0.0, 2.0], [0.004, 0.0, 2.0]])
    projected = stack.project(expected)
    near_both = projected[:, 0] + np.array([[0.0, 0.4], [0.0, -0.4]])
    blobs = [near_both, np.zeros((0, 2)), projected[:, 2]]
    labels, _ = label_blobs(stack, blobs, expected, 25.0)
    assert labels[:, 1].tolist() == [-1, -1]
    np.testing.assert_array_equal(labels, numpy_labels(stack, blobs, expected, 25.0))
    assert label_blobs(stack, [np.zeros((0, 2))] * 3, expected, 3.0)[0].tolist() == [[-1] * 3] * 2
