"""``planar_target``: the target's corners land where a homography from image features puts them.

Two checks of the ground truth. With the default light and defocus changes: SIFT matches
between the texture and the frame, a MAGSAC homography, and the target's corners mapped
through it within 1 px of the projected ground-truth corners (0.5 px on average; the
corners are an extrapolation from the matched features). With constant light and no
defocus: that homography refined by dense ECC alignment puts the corners within 0.1 px.
"""

import cv2
import numpy as np
import pytest

from services.geometry.camera import project_points
from services.geometry.se3 import transform_points
from services.synthetic import make_scene

ECC_LEVEL = 1
ECC_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 60, 1e-7)


def projected_corners(scene, frame) -> np.ndarray:
    """(4, 2) pixels of the target's corners under the ground-truth pose."""
    (_, _, T_cam_target), = frame.truth["cam0"]
    return project_points(transform_points(T_cam_target, scene.target.corners()), scene.cameras[0].K)


def corner_texels(scene) -> np.ndarray:
    """(4, 1, 2) texel coordinates of the target's corners."""
    corners = scene.target.corners()
    texels = (scene.target.texel_from_plane @ np.column_stack([corners[:, :2], np.ones(4)]).T).T
    return (texels[:, :2] / texels[:, 2:]).reshape(4, 1, 2)


def sift_homography(texture: np.ndarray, image: np.ndarray) -> np.ndarray:
    """(3, 3) homography texel -> pixel from SIFT matches (ratio test) and MAGSAC."""
    sift = cv2.SIFT_create(nfeatures=2000)
    texture_points, texture_descriptors = sift.detectAndCompute(texture, None)
    image_points, image_descriptors = sift.detectAndCompute(image, None)
    pairs = cv2.BFMatcher(cv2.NORM_L2).knnMatch(texture_descriptors, image_descriptors, k=2)
    good = [a for a, b in pairs if a.distance < 0.75 * b.distance]
    assert len(good) > 100
    source = np.float32([texture_points[m.queryIdx].pt for m in good])
    target = np.float32([image_points[m.trainIdx].pt for m in good])
    H, _ = cv2.findHomography(source, target, cv2.USAC_MAGSAC, 1.0)
    return H


@pytest.fixture(scope="module")
def scene():
    return make_scene("planar_target")


@pytest.mark.parametrize("index", [0, 170, 340])
def test_feature_homography_agrees_with_truth(scene, index):
    frame = scene.render(index)
    H = sift_homography(scene.texture, frame.images["cam0"])
    errors = np.linalg.norm(cv2.perspectiveTransform(corner_texels(scene), H).reshape(4, 2)
                            - projected_corners(scene, frame), axis=1)
    assert errors.max() < 1.0 and errors.mean() < 0.5


@pytest.mark.parametrize("index", [25, 400])
def test_dense_alignment_agrees_with_truth_to_a_tenth_of_a_pixel(index):
    scene = make_scene("planar_target", lighting=0.0, defocus=0.0, seed=3)
    frame = scene.render(index)
    image = frame.images["cam0"]
    H = sift_homography(scene.texture, image)
    corners = projected_corners(scene, frame)
    mask = np.zeros(image.shape, np.uint8)
    cv2.fillConvexPoly(mask, np.round(corners * 16).astype(np.int32), 255, cv2.LINE_8, 4)
    mask = cv2.erode(mask, np.ones((9, 9), np.uint8))
    scale = 2.0 ** ECC_LEVEL
    warp = (H @ np.diag([scale, scale, 1.0])).astype(np.float32)
    _, warp = cv2.findTransformECC(scene.target.levels[ECC_LEVEL], image, warp / warp[2, 2],
                                   cv2.MOTION_HOMOGRAPHY, ECC_CRITERIA, mask, 3)
    refined = warp.astype(np.float64) @ np.diag([1 / scale, 1 / scale, 1.0])
    errors = np.linalg.norm(cv2.perspectiveTransform(corner_texels(scene), refined).reshape(4, 2) - corners, axis=1)
    assert errors.max() < 0.1


def test_light_changes_over_time_and_is_constant_when_off():
    lit, flat = make_scene("planar_target"), make_scene("planar_target", lighting=0.0)
    gains = []
    for index in range(0, 600, 60):
        a, b = lit.render(index).images["cam0"].astype(float), flat.render(index).images["cam0"].astype(float)
        usable = (b > 40) & (b < 170)
        gains.append(np.median(a[usable] / b[usable]))
    assert max(gains) - min(gains) > 0.15
    assert make_scene("planar_target", lighting=0.0).render(5).images["cam0"].tobytes() == \
        flat.render(5).images["cam0"].tobytes()


def test_views_away_from_focus_are_blurred():
    sharp, defocused = make_scene("planar_target", defocus=0.0), make_scene("planar_target")
    distances = [defocused.camera_pose(i)[2, 3] for i in range(0, 900, 10)]
    near = int(np.argmin(distances)) * 10
    assert abs(1 / min(distances) - 1 / defocused.focus_m) > 1.0

    def sharpness(scene):
        return cv2.Laplacian(scene.render(near).images["cam0"], cv2.CV_64F).var()

    assert sharpness(defocused) < 0.7 * sharpness(sharp)


def test_texture_and_size_are_exposed(scene):
    assert scene.size_m == (0.297, 0.21)
    assert scene.texture.shape == (round(1024 * 0.21 / 0.297), 1024) and scene.texture.dtype == np.uint8
    assert np.ptp(scene.texture) > 200 and len(cv2.ORB_create(1000).detect(scene.texture)) >= 900


def test_a_static_camera_holds_its_first_pose_while_the_light_changes():
    still, moving = make_scene("planar_target", motion="static"), make_scene("planar_target")
    first = still.render(0)
    np.testing.assert_array_equal(first.truth["cam0"][0][2], moving.render(0).truth["cam0"][0][2])
    later = still.render(150)
    np.testing.assert_array_equal(later.truth["cam0"][0][2], first.truth["cam0"][0][2])
    assert not np.array_equal(moving.render(150).truth["cam0"][0][2], first.truth["cam0"][0][2])
    assert later.images["cam0"].tobytes() != first.images["cam0"].tobytes()
    assert make_scene("planar_target", motion="static", lighting=0.0).render(150).images["cam0"].tobytes() == \
        make_scene("planar_target", motion="static", lighting=0.0).render(0).images["cam0"].tobytes()


def test_an_unknown_motion_is_refused():
    with pytest.raises(ValueError, match="motion='spin'.*sway, static"):
        make_scene("planar_target", motion="spin")
