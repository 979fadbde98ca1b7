"""``markers``: the rendered markers sit where the ground truth says, to a fraction of a pixel.

Detector: cv2.aruco.ArucoDetector with CORNER_REFINE_SUBPIX. Its corners carry an inward bias
of its own (0.06 to 0.25 px per axis on an ideal axis-aligned marker, more for small or
blurred ones), so corners are held to median < 0.3 px and max < 1 px, and the mean of a
marker's four corners, where that bias cancels, to median < 0.05 px. A GT-visible marker
may go undetected only when a corner is within ``BORDER_PX`` of the image border (its quiet
zone is cut off) or it is seen at more than ``MAX_OBLIQUITY_DEG``.
"""

import cv2
import numpy as np
import pytest

from services.geometry.camera import project_points
from services.geometry.se3 import invert, transform_points
from services.synthetic import make_scene

INDICES = range(0, 900, 45)
BORDER_PX = 10
MAX_OBLIQUITY_DEG = 60.0


def detector(scene):
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    return cv2.aruco.ArucoDetector(scene.dictionary, params)


def visible(frame):
    """Marker id -> T_cam0_marker for the markers the ground truth lists."""
    return {int(child.split("/")[1]): T for _, child, T in frame.truth["cam0"]}


@pytest.fixture(scope="module")
def scene():
    return make_scene("markers")


@pytest.fixture(scope="module")
def detections(scene):
    """[(index, frame, {id: (4, 2) detected corners})] over ``INDICES``."""
    found = []
    for index in INDICES:
        frame = scene.render(index)
        corners, ids, _ = detector(scene).detectMarkers(frame.images["cam0"])
        ids = [] if ids is None else np.ravel(ids).tolist()
        found.append((index, frame, {i: c.reshape(4, 2) for i, c in zip(ids, corners, strict=True)}))
    return found


def test_detected_corners_match_projected_ground_truth(scene, detections):
    K = scene.cameras[0].K
    errors, centre_errors = [], []
    for _, frame, detected in detections:
        for marker_id, T_cam_marker in visible(frame).items():
            if marker_id in detected:
                corners = transform_points(T_cam_marker, scene.marker_corners[marker_id] -
                                           scene.marker_poses[marker_id][:3, 3])
                residual = detected[marker_id] - project_points(corners, K)
                errors.extend(np.linalg.norm(residual, axis=1))
                centre_errors.append(np.linalg.norm(residual.mean(axis=0)))
    assert len(centre_errors) >= 80
    assert np.median(errors) < 0.3 and np.max(errors) < 1.0
    assert np.median(centre_errors) < 0.05


def test_detected_ids_are_the_visible_ones(scene, detections):
    camera = scene.cameras[0]
    for index, frame, detected in detections:
        truth = visible(frame)
        assert set(detected) <= set(truth), index
        for marker_id in set(truth) - set(detected):
            T = truth[marker_id]
            pixels = project_points(transform_points(T, scene.marker_corners[marker_id] -
                                                     scene.marker_poses[marker_id][:3, 3]), camera.K)
            margin = min(pixels.min(), camera.width - 1 - pixels[:, 0].max(), camera.height - 1 - pixels[:, 1].max())
            obliquity = np.degrees(np.arccos(-T[:3, 2] @ T[:3, 3] / np.linalg.norm(T[:3, 3])))
            assert margin < BORDER_PX or obliquity > MAX_OBLIQUITY_DEG, (index, marker_id)


def test_path_shows_markers_at_useful_sizes_and_sometimes_loses_some(scene):
    camera = scene.cameras[0]
    counts, widths = [], []
    for index in range(0, 1800, 10):
        T_cam_board = invert(scene.camera_pose(index))
        count = 0
        for corners in scene.marker_corners.values():
            pixels = project_points(transform_points(T_cam_board, corners), camera.K)
            if np.all((pixels >= 0) & (pixels <= (camera.width - 1, camera.height - 1))):
                count += 1
                widths.append(np.ptp(pixels[:, 0]) / camera.width)
        counts.append(count)
    assert min(counts) < len(scene.marker_corners) and np.mean(np.array(counts) == len(scene.marker_corners)) > 0.5
    assert np.percentile(widths, 2) > 0.04 and np.percentile(widths, 98) < 0.32


def test_layout_matches_marker_length_and_truth(scene):
    L = scene.marker_length
    frame = scene.render(0)
    T_cam_board = invert(scene.camera_pose(0))
    for marker_id, corners in scene.marker_corners.items():
        assert np.allclose(np.linalg.norm(np.diff(corners, axis=0, append=corners[:1]), axis=1), L)
        assert np.allclose(corners.mean(axis=0), scene.marker_poses[marker_id][:3, 3])
    for _, child, T in frame.truth["cam0"]:
        marker_id = int(child.split("/")[1])
        assert np.allclose(T, T_cam_board @ scene.marker_poses[marker_id])


def test_other_dictionary_ids_and_length_render_detectably():
    scene = make_scene("markers", dictionary="DICT_6X6_250", ids=(200, 17, 42), marker_length=0.1, seed=5)
    for index in (0, 50, 100):
        frame = scene.render(index)
        _, ids, _ = detector(scene).detectMarkers(frame.images["cam0"])
        assert set(np.ravel(ids).tolist()) == set(visible(frame)) and len(visible(frame)) > 0


def test_the_markers_scene_settles_the_side_and_dictionary_of_its_markers_and_gives_its_board():
    scene = make_scene("markers", dictionary="DICT_5X5_50", ids=(3, 4), marker_length=0.1)
    fixtures = scene.fixtures()
    assert fixtures.settings == {"marker_length": 0.1, "dictionary": "DICT_5X5_50"}
    board = fixtures.marker_map
    assert board is not None and (board.name, board.dictionary, board.length) == ("board", "DICT_5X5_50", 0.1)
    assert list(board.poses) == [3, 4] and all(np.array_equal(board.poses[i], scene.marker_poses[i]) for i in (3, 4))
    assert fixtures.rig == scene.cameras and fixtures.bodies == {} and fixtures.target is None


def test_distance_lighting_and_supersampling_are_options_and_checked():
    L = 0.055
    scene = make_scene("markers", dictionary="DICT_APRILTAG_36h11", ids=(0, 1), marker_length=L,
                       distance=(0.3 / L, 1.0 / L), lighting=0.3, supersample=4, fps=5.0, seed=3)
    ranges, brightest, means = [], [], []
    for index in range(0, 150, 5):
        frame = scene.render(index)
        image = frame.images["cam0"]
        ranges += [np.linalg.norm(T[:3, 3]) for T in visible(frame).values()]
        brightest.append(int(image.max()))
        means.append(float(image.mean()))
    assert 0.28 < min(ranges) < 0.4 and 0.85 < max(ranges) < 1.1
    assert max(brightest) < 255 and max(means) > 1.15 * min(means)
    for bad in ({"distance": (16.0, 3.2)}, {"distance": (0.5, 3.0)}, {"distance": (3.0,)}, {"supersample": 0},
                {"supersample": 2.5}, {"lighting": 1.0}):
        with pytest.raises(ValueError, match=next(iter(bad))):
            make_scene("markers", **bad)


def test_supersampling_changes_the_edges_not_the_picture():
    sharp, fine = make_scene("markers", seed=4), make_scene("markers", seed=4, supersample=2)
    one, two = sharp.render(30).images["cam0"].astype(float), fine.render(30).images["cam0"].astype(float)
    assert np.abs(one - two).mean() < 2.0 and np.abs(one - two).max() > 20
    assert abs(one.mean() - two.mean()) < 0.2
