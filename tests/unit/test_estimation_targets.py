"""Image targets: the pixel-to-plane mapping, the pyramid's keypoints and the refusals of ``build_target``."""

import cv2
import numpy as np
import pytest

from services.detection.keypoints.detector import KeypointDetector
from services.estimation.targets.features import feature_params, keypoint_cap, make_extractor, to_grey
from services.estimation.targets.target import (
    MAX_LEVELS,
    MIN_LEVEL_SIDE,
    build_target,
    pyramid_features,
    target_levels,
    target_points,
)
from services.synthetic import make_scene
from services.synthetic.plane import texel_from_plane


@pytest.fixture(scope="module")
def scene():
    return make_scene("planar_target")


def test_pixel_centres_map_as_the_scene_renders_its_texture(scene):
    h, w = scene.texture.shape
    pixels = np.array([[0.0, 0.0], [w - 1, h - 1], [(w - 1) / 2, (h - 1) / 2], [-0.5, -0.5], [517.25, 3.5]])
    width_m = scene.size_m[0]
    height_m = h * width_m / w
    points = target_points(pixels, (w, h), width_m)
    texels = (texel_from_plane(scene.texture.shape, width_m, height_m)
              @ np.column_stack([points[:, :2], np.ones(len(points))]).T).T
    np.testing.assert_allclose(texels[:, :2] / texels[:, 2:], pixels, atol=1e-9)
    np.testing.assert_allclose(points[2], [0.0, 0.0, 0.0], atol=1e-15)
    np.testing.assert_allclose(points[3], [-width_m / 2, height_m / 2, 0.0])


def test_a_target_is_its_image_features_and_their_plane_points(scene):
    target = build_target("poster", scene.texture, 0.297)
    h, w = scene.texture.shape
    assert target.size_px == (w, h) and target.height_m == pytest.approx(0.297 * h / w)
    assert target.descriptors.dtype == np.uint8 and target.descriptors.shape == (len(target.keypoints), 32)
    assert set(np.unique(target.levels)) == {0, 1, 2}
    assert np.all((target.keypoints >= -0.5) & (target.keypoints <= [w - 0.5, h - 0.5]))
    np.testing.assert_allclose(target.points, target_points(target.keypoints, (w, h), 0.297))
    corners = target.corners()
    np.testing.assert_allclose(corners[0], [-0.1485, target.height_m / 2, 0.0])
    uv = np.array([[-0.5, -0.5, 1.0], [w - 0.5, h - 0.5, 1.0]]) @ target.plane_from_pixel().T
    np.testing.assert_allclose(uv[:, :2], corners[[0, 2], :2])


def test_sift_targets_carry_float_descriptors(scene):
    target = build_target("poster", scene.texture[:400, :600], 0.2, "sift")
    assert target.feature == "sift" and target.descriptors.dtype == np.float32
    assert target.descriptors.shape[1] == 128


def test_a_sift_target_is_every_keypoint_of_its_full_image_alone(scene):
    target = build_target("poster", scene.texture, 0.297, "sift")
    assert target_levels(target.detector) == 1 and not target.levels.any()
    found = cv2.SIFT.create(enable_precise_upscale=True).detect(scene.texture, None)
    assert len(found) < keypoint_cap(target.detector, scene.texture.shape)
    assert sorted(map(tuple, target.keypoints.tolist())) == sorted(k.pt for k in found)


def test_an_orb_target_keeps_its_pyramid_and_its_cap_per_level(scene):
    orb = feature_params("orb")
    assert target_levels(orb) == MAX_LEVELS
    assert keypoint_cap(orb, (2160, 3840)) == orb.max_count


@pytest.mark.parametrize(("shape", "cap"), [((480, 640), 2000), ((1024, 768), 5120), ((100, 100), 2000),
                                            ((2160, 3840, 3), 54000)])
def test_a_scale_space_cap_grows_with_the_image_area(shape, cap):
    assert keypoint_cap(feature_params("sift"), shape) == cap


def test_each_level_maps_its_pixels_back_to_the_full_image():
    seen = []

    def centre_only(grey):
        seen.append(grey.shape)
        h, w = grey.shape
        return np.array([[(w - 1) / 2, (h - 1) / 2], [0.0, 0.0]], np.float32), np.zeros((2, 32), np.uint8)

    image = np.zeros((720, 1280), np.uint8)
    keypoints, _, levels = pyramid_features(image, centre_only)
    assert seen == [(720, 1280), (360, 640), (180, 320)] and min(seen[-1]) >= MIN_LEVEL_SIDE
    np.testing.assert_array_equal(levels, [0, 0, 1, 1, 2, 2])
    np.testing.assert_allclose(keypoints[0::2], [[639.5, 359.5]] * 3)
    np.testing.assert_allclose(keypoints[1::2], [[0.0, 0.0], [0.5, 0.5], [1.5, 1.5]])


def test_grey_conversion_takes_colour_and_sixteen_bits():
    colour = np.zeros((4, 5, 3), np.uint8)
    colour[..., 2] = 255
    assert to_grey(colour).shape == (4, 5) and to_grey(colour)[0, 0] == 76
    assert to_grey(np.full((4, 5), 65535, np.uint16))[0, 0] == 255
    with pytest.raises(ValueError, match="uint8 or uint16"):
        to_grey(np.zeros((4, 5), np.float32))
    with pytest.raises(ValueError, match="shape"):
        to_grey(np.zeros((0, 5), np.uint8))


@pytest.mark.parametrize("width", [0.0, -1.0, float("nan"), float("inf"), True])
def test_a_bad_width_is_refused(scene, width):
    with pytest.raises(ValueError, match="positive number of metres"):
        build_target("poster", scene.texture, width)


def test_tiny_and_textureless_images_are_refused():
    with pytest.raises(ValueError, match="at least 32 px"):
        build_target("tiny", np.zeros((20, 200), np.uint8), 0.1)
    with pytest.raises(ValueError, match="no keypoints"):
        build_target("grey", np.full((300, 400), 128, np.uint8), 0.1)


def test_unknown_features_are_refused():
    with pytest.raises(ValueError, match="orb, sift"):
        make_extractor("surf")


@pytest.mark.parametrize("feature", ["orb", "sift"])
def test_a_target_is_described_by_the_keypoint_detector_it_records(scene, feature):
    image = scene.texture[:400, :600]
    target = build_target("poster", image, 0.2, feature)
    assert target.detector == feature_params(feature) and target.feature == feature
    found = KeypointDetector(target.detector).detect(image)
    finest = target.levels == 0
    np.testing.assert_array_equal(target.keypoints[finest], found.points)
    np.testing.assert_array_equal(target.descriptors[finest], found.descriptors)
