"""``ir_rig``: blobs sit on the projected sphere centres (through the distortion), hidden ones are gone.

Blob centres are intensity-weighted centroids (background subtracted) of the connected
components above a threshold. Only spheres inside the image and at least ``ISOLATION_PX``
from every other sphere's projection are compared, so merged blobs do not count.
"""

import itertools

import cv2
import numpy as np
import pytest

from services.geometry.camera import project_points
from services.geometry.se3 import invert, transform_points
from services.synthetic import make_scene
from services.synthetic.ir_rig import (
    ARC_DISTANCES_M,
    ARC_HALF_ANGLE_DEG,
    BACKGROUND,
    BODY_DEPTH_M,
    LAYOUTS,
    LFRAME,
    LFRAME_BODY,
    SPHERE_PEAK,
    WAND_BODY,
)
from tests.accuracy.stereo_losses import HARD

INDICES = range(0, 1500, 25)
ISOLATION_PX = 12.0
THRESHOLD = 60


def blob_centres(image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, 2) weighted centroids and (N,) areas (px, lit fraction summed) of the bright blobs of ``image``."""
    count, labels = cv2.connectedComponents((image > THRESHOLD).astype(np.uint8))
    weight = np.maximum(image.astype(np.float64) - BACKGROUND, 0.0).ravel()
    ys, xs = np.indices(image.shape)
    mass = np.bincount(labels.ravel(), weight, count)
    centres = np.stack([np.bincount(labels.ravel(), weight * xs.ravel(), count),
                        np.bincount(labels.ravel(), weight * ys.ravel(), count)], axis=1) / mass[:, None]
    return centres[1:], mass[1:] / (SPHERE_PEAK - BACKGROUND)


def projected_spheres(scene, camera, index):
    """[(body, sphere, (2,) pixel, depth)] of every sphere in front of ``camera``."""
    T_cam_world = invert(camera.T_rig_camera)
    found = []
    for body, T_world_body in scene.body_poses(index).items():
        centres = transform_points(T_cam_world @ T_world_body, scene.bodies[body])
        for j, (pixel, depth) in enumerate(zip(project_points(centres, camera.K, camera.dist), centres[:, 2],
                                               strict=True)):
            found.append((body, j, pixel, depth))
    return found


@pytest.fixture(scope="module")
def scene():
    return make_scene("ir_rig")


@pytest.fixture(scope="module")
def matches(scene):
    """[(hidden?, distance to the nearest blob px, blob area px, expected area px)] for isolated spheres."""
    rows = []
    for index in INDICES:
        frame = scene.render(index)
        hidden = scene.occlusions(index)
        for camera in scene.cameras:
            blobs, areas = blob_centres(frame.images[camera.name])
            spheres = projected_spheres(scene, camera, index)
            pixels = np.array([s[2] for s in spheres])
            for body, j, pixel, depth in spheres:
                others = np.linalg.norm(pixels - pixel, axis=1)
                inside = np.all((pixel > 5) & (pixel < (camera.width - 6, camera.height - 6)))
                if not inside or np.sort(others)[1] < ISOLATION_PX:
                    continue
                distances = np.linalg.norm(blobs - pixel, axis=1)
                nearest = int(np.argmin(distances))
                expected_area = np.pi * (camera.K[0, 0] * scene.sphere_radius / depth) ** 2
                rows.append(((camera.name, body, j) in hidden, distances[nearest], areas[nearest], expected_area))
    return rows


def test_blob_centroids_match_projected_sphere_centres(matches):
    errors = np.array([distance for hidden, distance, _, _ in matches if not hidden])
    assert len(errors) > 500
    assert np.median(errors) < 0.1 and np.max(errors) < 0.3


def test_blob_area_follows_sphere_radius_and_depth(matches):
    ratios = np.array([area / expected for hidden, _, area, expected in matches if not hidden])
    assert np.median(ratios) == pytest.approx(1.0, abs=0.05)
    assert np.percentile(ratios, 5) > 0.85 and np.percentile(ratios, 95) < 1.15


def test_hidden_spheres_leave_no_blob(matches):
    hidden = [distance for is_hidden, distance, _, _ in matches if is_hidden]
    assert len(hidden) >= 3
    assert min(hidden) > 5.0


def test_occlusion_hides_one_sphere_in_one_camera_now_and_then(scene):
    hidden = [scene.occlusions(index) for index in range(0, 3000, 5)]
    assert all(len(h) <= 1 for h in hidden)
    assert 0.1 < np.mean([len(h) == 1 for h in hidden]) < 0.4
    assert make_scene("ir_rig", occlusion_rate=0.0).occlusions(10) == set()


def test_truth_lists_every_body_under_every_camera(scene):
    frame = scene.render(7)
    poses = scene.body_poses(7)
    assert len(poses) == 3
    for camera in scene.cameras:
        assert [(p, c) for p, c, _ in frame.truth[camera.name]] == [("world", f"body/{name}") for name in poses]
        assert all(np.array_equal(T, poses[c.split("/")[1]]) for _, c, T in frame.truth[camera.name])


def test_layouts_are_distinct_and_unambiguous():
    triangles = {}
    for name, spheres in LAYOUTS.items():
        assert 3 <= len(spheres) <= 6
        distances = np.sort([np.linalg.norm(a - b) for a, b in itertools.combinations(spheres, 2)])
        assert distances[0] >= 0.05 and np.diff(distances).min() >= 0.004, name
        assert np.linalg.svd(spheres - spheres.mean(axis=0), compute_uv=False)[1] > 0.03, name
        triangles[name] = np.array([sorted(np.linalg.norm(a - b) for a, b in itertools.combinations(t, 2))
                                    for t in itertools.combinations(spheres, 3)])
    for a, b in itertools.combinations(triangles, 2):
        assert np.abs(triangles[a][:, None] - triangles[b][None]).max(axis=2).min() >= 0.005, (a, b)


def test_rig_geometry():
    scene = make_scene("ir_rig", camera_count=3, baseline=0.25, convergence=3.0, distortion=False)
    assert [c.name for c in scene.cameras] == ["cam0", "cam1", "cam2"]
    for i, camera in enumerate(scene.cameras):
        T = camera.T_rig_camera
        assert np.allclose(T[:3, 3], [(i - 1) * 0.25, 0, 0])
        ray_to_convergence = np.array([0, 0, 3.0]) - T[:3, 3]
        assert np.allclose(T[:3, 2], ray_to_convergence / np.linalg.norm(ray_to_convergence))
        assert T[1, 1] > 0.99 and np.array_equal(camera.dist, np.zeros(5))
    distorted = make_scene("ir_rig").cameras
    assert all(np.abs(c.dist[:2]).max() > 0 for c in distorted)
    assert not np.array_equal(distorted[0].K, distorted[1].K)


def test_wand_motion_waves_one_collinear_wand_through_the_volume():
    scene = make_scene("ir_rig", motion="wand", camera_count=3, wand_spheres=(0.0, 0.2, 0.6))
    assert list(scene.bodies) == [WAND_BODY]
    spheres = scene.bodies[WAND_BODY]
    assert np.allclose(spheres[:, 1:], 0.0) and np.allclose(spheres[:, 0], [0.0, 0.2, 0.6])
    frame = scene.render(11)
    assert [(p, c) for p, c, _ in frame.truth["cam2"]] == [("world", f"body/{WAND_BODY}")]
    middles, directions = [], []
    for index in range(0, 3000, 10):
        T = scene.body_poses(index)[WAND_BODY]
        middles.append(transform_points(T, spheres).mean(axis=0))
        directions.append(T[:3, 0])
    middles, directions = np.array(middles), np.array(directions)
    assert middles[:, 2].min() > 1.3 and middles[:, 2].max() < 3.5
    assert np.ptp(middles[:, 0]) > 1.2 and np.ptp(middles[:, 1]) > 0.8 and np.ptp(middles[:, 2]) > 1.2
    assert np.abs(directions).max(axis=0).min() > 0.9
    assert make_scene("ir_rig").bodies.keys() == {"wand", "tool", "head"}


def test_lframe_motion_lies_still_on_the_floor_in_view():
    scene = make_scene("ir_rig", motion="lframe", camera_count=3)
    assert list(scene.bodies) == [LFRAME_BODY]
    T = scene.body_poses(0)[LFRAME_BODY]
    assert np.array_equal(T, scene.body_poses(500)[LFRAME_BODY])
    assert np.allclose(T[:3, 2], [0.0, -1.0, 0.0])
    spheres = transform_points(T, LFRAME)
    assert np.ptp(spheres[:, 1]) < 1e-12
    for camera in scene.cameras:
        pixels = project_points(transform_points(invert(camera.T_rig_camera), spheres), camera.K, camera.dist)
        assert np.all((pixels > 10) & (pixels < (camera.width - 10, camera.height - 10)))


@pytest.mark.parametrize(("options", "message"), [
    ({"motion": "walk"}, "motion='walk'"),
    ({"wand_spheres": (0.1, 0.3, 0.5)}, r"wand_spheres=\(0.1, 0.3, 0.5\)"),
    ({"wand_spheres": (0.0, 0.5, 0.2)}, "wand_spheres="),
    ({"wand_spheres": (0.0,)}, "wand_spheres="),
    ({"wand_spheres": "0,1"}, "wand_spheres="),
])
def test_invalid_wand_options_are_rejected(options, message):
    with pytest.raises(ValueError, match=f"option {message}"):
        make_scene("ir_rig", **options)


def test_the_hard_preset_is_three_arc_cameras_two_bodies_small_spheres_at_120_hz():
    scene = make_scene("ir_rig", **HARD)
    assert len(scene.cameras) == 3 and list(scene.bodies) == ["tool", "head"]
    assert scene.sphere_radius == 0.0075 and scene.time_s(120) == pytest.approx(1.0)
    assert scene.options.layout == "arc" and scene.options.strays == 2 and scene.options.spin > 1


def test_arc_cameras_stand_around_the_volume_at_different_distances_each_with_its_distortion():
    scene = make_scene("ir_rig", camera_count=3, layout="arc")
    centre = np.array([0.0, 0.0, BODY_DEPTH_M])
    distances, azimuths = [], []
    for camera in scene.cameras:
        eye, forward = camera.T_rig_camera[:3, 3], camera.T_rig_camera[:3, 2]
        distances.append(np.linalg.norm(centre - eye))
        assert np.allclose(forward, (centre - eye) / distances[-1])
        azimuths.append(np.degrees(np.arctan2(eye[0] - centre[0], centre[2] - eye[2])))
        assert eye[1] < 0.0  # raised above the volume (y is down)
    assert np.allclose(sorted(distances), np.linspace(*ARC_DISTANCES_M, 3))
    assert np.allclose(azimuths, [-ARC_HALF_ANGLE_DEG, 0.0, ARC_HALF_ANGLE_DEG])
    dist = np.array([c.dist for c in scene.cameras])
    assert np.all(np.abs(dist[:, 0]) > 0) and len({tuple(d) for d in dist}) == 3
    bar = make_scene("ir_rig", camera_count=3)
    assert [c.K.tolist() for c in bar.cameras] == [c.K.tolist() for c in scene.cameras]


def test_strays_come_and_go_near_a_body_and_are_drawn_where_they_project():
    scene = make_scene("ir_rig", **HARD)
    counts = [len(scene.strays_at(index)) for index in range(0, 360, 4)]
    assert max(counts) == 2 and min(counts) < 2 and 0 < np.mean(counts) < 2
    assert len(make_scene("ir_rig").strays_at(10)) == 0
    index = next(i for i in range(0, 360, 4) if len(scene.strays_at(i)))
    strays = scene.strays_at(index)
    spheres = np.concatenate([transform_points(T, scene.bodies[name]) for name, T in scene.body_poses(index).items()])
    gaps = np.linalg.norm(strays[:, None] - spheres[None], axis=2).min(axis=1)
    assert np.all(gaps < 0.2)
    frame = scene.render(index)
    for camera in scene.cameras:
        blobs, areas = blob_centres(frame.images[camera.name])
        pixels = project_points(transform_points(invert(camera.T_rig_camera), strays), camera.K, camera.dist)
        for pixel in pixels:
            distance = np.linalg.norm(blobs - pixel, axis=1)
            assert distance.min() < 0.5, (camera.name, pixel)
            assert areas[distance.argmin()] < np.pi * (camera.K[0, 0] * scene.sphere_radius / 1.5) ** 2


def test_spin_scales_the_turning_and_the_hard_scene_merges_spheres_in_some_views():
    calm, fast = make_scene("ir_rig", spin=1.0), make_scene("ir_rig", spin=3.0)
    for name in calm.bodies:
        assert np.allclose(fast.paths[name].rotvec(0.7), 3.0 * calm.paths[name].rotvec(0.7))
        assert np.array_equal(fast.paths[name].position(0.7), calm.paths[name].position(0.7))
    scene = make_scene("ir_rig", **HARD)
    merged = 0
    for index in range(0, 360, 3):
        for camera in scene.cameras:
            spheres = projected_spheres(scene, camera, index)
            for (body_a, _, pixel_a, depth_a), (body_b, _, pixel_b, depth_b) in itertools.combinations(spheres, 2):
                radii = camera.K[0, 0] * scene.sphere_radius * (1.0 / depth_a + 1.0 / depth_b)
                merged += body_a == body_b and np.linalg.norm(pixel_a - pixel_b) < radii
    assert merged >= 5


@pytest.mark.parametrize(("options", "message"), [
    ({"layout": "ring"}, "layout='ring'"),
    ({"layouts": ("tool", "hat")}, "layouts="),
    ({"layouts": ("tool", "tool")}, "layouts="),
    ({"spin": -1.0}, "spin="),
    ({"strays": -1}, "strays="),
])
def test_invalid_hard_scene_options_are_rejected(options, message):
    with pytest.raises(ValueError, match=f"option {message}"):
        make_scene("ir_rig", **options)
