"""The frame graph: composition and inversion along paths, lookups, cycles, and the errors it gives."""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.geometry.frames import (
    DisconnectedFramesError,
    FrameError,
    FrameGraph,
    InconsistentCycleError,
    UnknownFrameError,
)
from services.geometry.rotation import matrix_from_rotvec
from services.geometry.se3 import check_transform, invert, make_transform, transform_points


def random_transform(rng: np.random.Generator) -> np.ndarray:
    return make_transform(matrix_from_rotvec(rng.normal(0.0, 1.0, 3)), rng.uniform(-2.0, 2.0, 3))


def rot_z(degrees: float) -> np.ndarray:
    c, s = math.cos(math.radians(degrees)), math.sin(math.radians(degrees))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def stereo_rig() -> tuple[FrameGraph, dict[str, np.ndarray]]:
    """world <- rig <- cam0, rig <- cam1, cam0 <- marker; edges and their matrices."""
    rng = np.random.default_rng(7)
    T = {name: random_transform(rng) for name in ("world_rig", "rig_cam0", "rig_cam1", "cam0_marker")}
    graph = FrameGraph()
    graph.add("world", "rig", T["world_rig"])
    graph.add("rig", "cam0", T["rig_cam0"])
    graph.add("rig", "cam1", T["rig_cam1"])
    graph.add("cam0", "marker", T["cam0_marker"])
    return graph, T


def test_lookups_compose_and_invert_as_se3_does_by_hand():
    graph, T = stereo_rig()
    assert np.allclose(graph.transform("rig", "cam0"), T["rig_cam0"], atol=1e-15)
    assert np.allclose(graph.transform("cam0", "cam1"), invert(T["rig_cam0"]) @ T["rig_cam1"], atol=1e-12)
    assert np.allclose(graph.transform("world", "marker"),
                       T["world_rig"] @ T["rig_cam0"] @ T["cam0_marker"], atol=1e-12)
    assert np.allclose(graph.transform("cam1", "marker"),
                       invert(T["rig_cam1"]) @ T["rig_cam0"] @ T["cam0_marker"], atol=1e-12)
    assert np.allclose(graph.transform("marker", "world"),
                       np.linalg.inv(T["world_rig"] @ T["rig_cam0"] @ T["cam0_marker"]), atol=1e-12)


def test_a_lookup_and_its_reverse_are_inverses_and_map_points_consistently():
    graph, _ = stereo_rig()
    T_marker_cam1 = graph.transform("marker", "cam1")
    assert np.allclose(T_marker_cam1 @ graph.transform("cam1", "marker"), np.eye(4), atol=1e-12)
    points_cam1 = np.random.default_rng(1).uniform(-1.0, 1.0, (5, 3))
    by_steps = points_cam1
    for a, b in (("rig", "cam1"), ("cam0", "rig"), ("marker", "cam0")):
        by_steps = transform_points(graph.transform(a, b), by_steps)
    assert np.allclose(transform_points(T_marker_cam1, points_cam1), by_steps, atol=1e-12)
    assert np.array_equal(graph.transform("cam1", "cam1"), np.eye(4))


def test_hand_worked_chain():
    """b is a turned 90 degrees about z and 1 m along a's x; c is 2 m along b's x: c's origin sits at (1, 2, 0) in a."""
    graph = FrameGraph()
    graph.add("a", "b", make_transform(rot_z(90.0), (1.0, 0.0, 0.0)))
    graph.add("b", "c", make_transform(np.eye(3), (2.0, 0.0, 0.0)))
    T_a_c = graph.transform("a", "c")
    assert np.allclose(T_a_c[:3, 3], (1.0, 2.0, 0.0), atol=1e-15)
    assert np.allclose(T_a_c[:3, :3], rot_z(90.0), atol=1e-15)
    assert np.allclose(transform_points(T_a_c, [[1.0, 0.0, 0.0]]), [[1.0, 3.0, 0.0]], atol=1e-15)
    T_c_a = graph.transform("c", "a")
    assert np.allclose(transform_points(T_c_a, [[0.0, 0.0, 0.0]]), [[-2.0, 1.0, 0.0]], atol=1e-15)


def test_two_toed_in_cameras_on_a_bar_see_each_other_where_the_bar_puts_them():
    """Cameras 0.3 m apart on a bar, each turned 10 degrees about y towards the middle (a stereo IR bar)."""
    def turned_y(degrees: float) -> np.ndarray:
        c, s = math.cos(math.radians(degrees)), math.sin(math.radians(degrees))
        return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])

    graph = FrameGraph()
    graph.add("rig", "cam0", make_transform(turned_y(10.0), (-0.15, 0.0, 0.0)))
    graph.add("rig", "cam1", make_transform(turned_y(-10.0), (0.15, 0.0, 0.0)))
    T_cam0_cam1 = graph.transform("cam0", "cam1")
    assert np.allclose(T_cam0_cam1[:3, :3], turned_y(-20.0), atol=1e-12)
    assert np.isclose(np.linalg.norm(T_cam0_cam1[:3, 3]), 0.3, atol=1e-12)
    c, s = math.cos(math.radians(10.0)), math.sin(math.radians(10.0))
    assert np.allclose(T_cam0_cam1[:3, 3], (0.3 * c, 0.0, 0.3 * s), atol=1e-12)


def test_every_pair_of_a_random_tree_matches_its_absolute_poses():
    """Frames with known poses in a hidden world, joined by a random tree whose edges point either way."""
    rng = np.random.default_rng(3)
    names = [f"f{i}" for i in range(12)]
    T_world = {name: random_transform(rng) for name in names}
    graph = FrameGraph()
    for i, name in enumerate(names[1:], start=1):
        other = names[int(rng.integers(i))]
        parent, child = (other, name) if rng.random() < 0.5 else (name, other)
        graph.add(parent, child, invert(T_world[parent]) @ T_world[child])
    for a in names:
        for b in names:
            assert np.allclose(graph.transform(a, b), invert(T_world[a]) @ T_world[b], atol=1e-9), (a, b)


def test_paths_run_through_the_tree_either_way_round():
    graph, _ = stereo_rig()
    assert graph.path("cam1", "marker") == ["cam1", "rig", "cam0", "marker"]
    assert graph.path("marker", "world") == ["marker", "cam0", "rig", "world"]
    assert graph.path("rig", "rig") == ["rig"]
    assert graph.frames() == ["world", "rig", "cam0", "cam1", "marker"]
    assert "cam1" in graph and "cam9" not in graph
    assert [(p, c) for p, c, _ in graph.edges()] == [("world", "rig"), ("rig", "cam0"), ("rig", "cam1"),
                                                     ("cam0", "marker")]


def test_an_unknown_frame_is_named_with_the_known_ones():
    graph, _ = stereo_rig()
    with pytest.raises(UnknownFrameError, match=r"unknown frame 'cam9' \(known: 'cam0', 'cam1', 'marker'"):
        graph.transform("cam0", "cam9")
    with pytest.raises(UnknownFrameError, match="unknown frame 'nowhere'"):
        graph.path("nowhere", "rig")
    with pytest.raises(UnknownFrameError, match="known: none"):
        FrameGraph().transform("a", "b")


def test_frames_in_separate_trees_are_reported_with_what_each_reaches():
    graph, _ = stereo_rig()
    graph.add("map", "keyframe0", np.eye(4))
    with pytest.raises(DisconnectedFramesError,
                       match=r"no transform chain from frame 'cam1' to frame 'keyframe0'.*'keyframe0' to 'keyframe0', "
                             r"'map'"):
        graph.transform("cam1", "keyframe0")
    graph.add("marker", "map", np.eye(4))  # anchoring the map joins the trees
    assert graph.path("cam1", "keyframe0") == ["cam1", "rig", "cam0", "marker", "map", "keyframe0"]


def test_an_edge_closing_a_cycle_is_checked_not_stored():
    graph, T = stereo_rig()
    edges = len(graph.edges())
    T_cam0_cam1 = invert(T["rig_cam0"]) @ T["rig_cam1"]
    graph.add("cam0", "cam1", T_cam0_cam1)
    graph.add("cam1", "rig", invert(T["rig_cam1"]))  # the same edge, the other way round
    graph.add("rig", "cam0", T["rig_cam0"])  # the same edge again
    assert len(graph.edges()) == edges
    assert graph.path("cam0", "cam1") == ["cam0", "rig", "cam1"]

    moved = T_cam0_cam1.copy()
    moved[0, 3] += 0.002
    with pytest.raises(InconsistentCycleError,
                       match=r"T_cam0_cam1 disagrees with the chain cam0 -> rig -> cam1 .* translation off by 0.002 m"):
        graph.add("cam0", "cam1", moved)
    turned = T_cam0_cam1 @ make_transform(rot_z(0.5), (0.0, 0.0, 0.0))
    with pytest.raises(InconsistentCycleError, match=r"rotation off by 0.00873 rad"):
        graph.add("cam0", "cam1", turned)
    assert len(graph.edges()) == edges
    assert np.allclose(graph.transform("cam0", "cam1"), T_cam0_cam1, atol=1e-12)


def test_the_cycle_tolerance_is_the_graph_s_choice():
    T = make_transform(np.eye(3), (0.3, 0.0, 0.0))
    nudged = make_transform(rot_z(0.01), (0.3005, 0.0, 0.0))  # 0.5 mm, 0.17 mrad apart
    strict, loose = FrameGraph(), FrameGraph(tolerance_rad=1e-3, tolerance_m=1e-3)
    for graph in (strict, loose):
        graph.add("rig", "cam0", np.eye(4))
        graph.add("rig", "cam1", T)
    loose.add("cam0", "cam1", nudged)
    with pytest.raises(InconsistentCycleError):
        strict.add("cam0", "cam1", nudged)


@pytest.mark.parametrize(("parent", "child", "says"), [
    ("", "cam0", "non-empty strings, got ''"),
    ("rig", None, "non-empty strings, got None"),
    ("cam0", "cam0", "two different frames, got 'cam0' twice"),
])
def test_bad_frame_names_are_refused(parent, child, says: str):
    with pytest.raises(FrameError, match=says):
        FrameGraph().add(parent, child, np.eye(4))


def reflection() -> np.ndarray:
    return np.diag([1.0, 1.0, -1.0, 1.0])


def scaled() -> np.ndarray:
    return np.diag([2.0, 2.0, 2.0, 1.0])


def projective() -> np.ndarray:
    T = np.eye(4)
    T[3, 2] = 0.1
    return T


def not_finite() -> np.ndarray:
    T = np.eye(4)
    T[0, 3] = np.nan
    return T


@pytest.mark.parametrize(("matrix", "says"), [
    (np.eye(3), r"T_rig_cam0 must have shape \(4, 4\), got \(3, 3\)"),
    (np.eye(4)[:3], r"must have shape \(4, 4\), got \(3, 4\)"),
    (np.eye(4).ravel(), r"got \(16,\)"),
    (reflection(), r"T_rig_cam0\[:3, :3\] must be a proper rotation \(det \+1\), got det -1"),
    (scaled(), r"must be orthonormal \(R\^T R = I\), off by 3"),
    (projective(), r"must have last row \(0, 0, 0, 1\), got \(0.0, 0.0, 0.1, 1.0\)"),
    (not_finite(), "must be finite"),
])
def test_matrices_that_are_not_proper_rigid_transforms_are_refused(matrix: np.ndarray, says: str):
    graph = FrameGraph()
    with pytest.raises(ValueError, match=says):
        graph.add("rig", "cam0", matrix)
    assert graph.frames() == []


def test_a_rotation_from_quaternion_round_off_passes_the_rigid_check():
    T = random_transform(np.random.default_rng(5))
    assert check_transform(T.tolist(), "T").dtype == np.float64
    T[:3, :3] *= 1 + 1e-9
    assert check_transform(T, "T") is not None


def test_the_graph_keeps_its_own_copy_of_each_edge():
    T = make_transform(np.eye(3), (1.0, 0.0, 0.0))
    graph = FrameGraph()
    graph.add("a", "b", T)
    T[0, 3] = 5.0
    graph.edges()[0][2][0, 3] = 7.0
    graph.transform("a", "b")[0, 3] = 9.0
    assert graph.transform("a", "b")[0, 3] == 1.0
