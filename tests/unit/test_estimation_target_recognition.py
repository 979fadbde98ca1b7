"""Recognition of an image target in one frame, scored against the ``planar_target`` scene's ground truth.

The target is built from the scene's own texture; every 20th of the first 600 frames (near and far,
tilted, defocused, under changing light) is recognised and its pose compared with the truth. Run with
``-s`` to print the figures (docs/feature-targets.md quotes them).
"""

import cv2
import numpy as np
import pytest

from services.estimation.targets.features import make_extractor
from services.estimation.targets.recognition import (
    RecognitionOptions,
    RecognitionStatus,
    TargetRecognizer,
    make_matcher,
    match_descriptors,
)
from services.estimation.targets.target import build_target
from services.geometry.camera import intrinsics, undistort_pixels
from services.geometry.evaluation import pose_error
from services.synthetic import make_scene
from tests.object_box import HAND_CHECKED_TOP_LEFT, OUTLINE, SCENE_FOV_DEG, box_images, box_outline

FRAMES = range(0, 600, 20)
BARS = {"orb": (0.2, 0.05), "sift": (0.15, 0.05)}
"""Per feature: the largest median rotation error (deg) and translation error (% of distance) accepted."""
DIST = np.array([-0.28, 0.09, 0.0005, -0.0003, -0.01])


@pytest.fixture(scope="module")
def scene():
    return make_scene("planar_target")


@pytest.fixture(scope="module")
def frames(scene):
    return [scene.render(i) for i in FRAMES]


def errors(recognizer, frames, K, dist=None, distort=None):
    """(rotation errors deg, translation errors % of distance) of every frame, all recognised."""
    extract = make_extractor(recognizer.target.feature)
    rotation, translation = [], []
    for frame in frames:
        (_, _, T_true), = frame.truth["cam0"]
        image = frame.images["cam0"] if distort is None else distort(frame.images["cam0"])
        result = recognizer.recognise_image(image, K, dist, extract)
        assert result.status is RecognitionStatus.RECOGNISED, (frame.index, result.status, result.inliers)
        angle, distance = pose_error(result.T_camera_target, T_true)
        rotation.append(np.degrees(angle))
        translation.append(100 * distance / np.linalg.norm(T_true[:3, 3]))
    return np.array(rotation), np.array(translation)


@pytest.mark.slow
@pytest.mark.parametrize("feature", ["orb", "sift"])
def test_the_scene_target_is_recognised_in_every_frame_within_the_bars(scene, frames, feature):
    recognizer = TargetRecognizer(build_target("poster", scene.texture, scene.size_m[0], feature))
    rotation, translation = errors(recognizer, frames, scene.cameras[0].K)
    print(f"\n{feature}: {len(frames)} frames, rotation median {np.median(rotation):.3f} deg "
          f"(p90 {np.percentile(rotation, 90):.3f}, max {rotation.max():.3f}); translation median "
          f"{np.median(translation):.3f} % of distance (p90 {np.percentile(translation, 90):.3f}, "
          f"max {translation.max():.3f})")
    max_rotation, max_translation = BARS[feature]
    assert np.median(rotation) <= max_rotation and np.median(translation) <= max_translation
    assert rotation.max() < 5 * max_rotation and translation.max() < 5 * max_translation


def test_a_result_carries_its_inliers_homography_and_covariance(scene, frames):
    target = build_target("poster", scene.texture, scene.size_m[0])
    K = scene.cameras[0].K
    extract = make_extractor("orb")
    points, descriptors = extract(frames[3].images["cam0"])
    result = TargetRecognizer(target).recognise(points, descriptors, K)
    assert result.recognised and result.target == "poster"
    assert 15 <= result.inliers == len(result.inlier_frame) == len(result.inlier_target) <= result.matches
    np.testing.assert_allclose(result.inlier_pixels, points[result.inlier_frame], atol=1e-4)
    T = result.T_camera_target
    projected = (target.points[result.inlier_target] @ T[:3, :3].T + T[:3, 3]) @ K.T
    residuals = projected[:, :2] / projected[:, 2:] - result.inlier_pixels
    assert np.sqrt(np.mean(np.sum(residuals**2, axis=1))) == pytest.approx(result.rms_px)
    assert result.rms_px < 1.5
    mapped = cv2.perspectiveTransform(target.keypoints[result.inlier_target].reshape(-1, 1, 2).astype(np.float64),
                                      result.homography).reshape(-1, 2)
    assert np.median(np.linalg.norm(mapped - result.inlier_pixels, axis=1)) < 1.5
    covariance = result.covariance
    assert covariance.shape == (6, 6) and np.allclose(covariance, covariance.T)
    assert np.all(np.linalg.eigvalsh(covariance) > 0)
    (_, _, T_true), = frames[3].truth["cam0"]
    assert np.linalg.norm(T[:3, 3] - T_true[:3, 3]) < 6 * np.sqrt(np.trace(covariance[:3, :3]))


def test_distorted_frames_are_undistorted_before_the_pose(scene, frames):
    K = scene.cameras[0].K
    h, w = frames[0].images["cam0"].shape
    grid = np.stack(np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64)), axis=-1)
    ideal = undistort_pixels(grid.reshape(-1, 2), K, DIST).reshape(h, w, 2).astype(np.float32)

    def distort(image):
        return cv2.remap(image, ideal[..., 0], ideal[..., 1], cv2.INTER_LINEAR, borderValue=110)

    recognizer = TargetRecognizer(build_target("poster", scene.texture, scene.size_m[0], "sift"))
    rotation, translation = errors(recognizer, frames[::3], K, DIST, distort)
    assert np.median(rotation) < 0.2 and np.median(translation) < 0.1
    ignored = []
    for frame in frames[::3]:
        result = recognizer.recognise_image(distort(frame.images["cam0"]), K)
        if result.recognised:
            ignored.append(np.degrees(pose_error(result.T_camera_target, frame.truth["cam0"][0][2])[0]))
    assert np.median(ignored) > 3 * np.median(rotation)


def test_a_frame_without_the_target_gives_no_pose(scene):
    recognizer = TargetRecognizer(build_target("poster", scene.texture, scene.size_m[0]))
    room = make_scene("room")
    for index in (0, 100, 200):
        image = room.render(index).images["cam0"]
        result = recognizer.recognise_image(image, intrinsics(image.shape[1], image.shape[0], 60.0))
        assert not result.recognised and result.T_camera_target is None and result.covariance is None
        assert result.status in (RecognitionStatus.TOO_FEW_MATCHES, RecognitionStatus.TOO_FEW_INLIERS,
                                RecognitionStatus.NO_POSE)
    grey = np.full((480, 640), 110, np.uint8)
    result = recognizer.recognise_image(grey, intrinsics(640, 480, 60.0))
    assert result.status is RecognitionStatus.NO_FEATURES and result.T_camera_target is None


def test_descriptors_of_another_kind_are_no_features(scene, frames):
    recognizer = TargetRecognizer(build_target("poster", scene.texture, scene.size_m[0]))
    points, descriptors = make_extractor("sift")(frames[0].images["cam0"])
    assert recognizer.recognise(points, descriptors, scene.cameras[0].K).status is RecognitionStatus.NO_FEATURES


def test_cross_check_keeps_mutual_best_matches_only():
    rng = np.random.default_rng(2)
    train = rng.integers(0, 256, (50, 32), dtype=np.uint8)
    query = np.concatenate([train[:10], train[:1]])
    matcher = cv2.BFMatcher(cv2.NORM_HAMMING)
    plain = match_descriptors(matcher, query, train, 0.8)
    np.testing.assert_array_equal(plain, [[i, i] for i in range(10)] + [[10, 0]])
    crossed = match_descriptors(matcher, query, train, 0.8, cross_check=True)
    assert len(crossed) == 10 and set(map(tuple, crossed)) <= set(map(tuple, plain))


def test_an_exact_float_matcher_finds_the_true_nearest_neighbours():
    rng = np.random.default_rng(3)
    train = rng.random((300, 128), np.float32)
    query = train[:40] + rng.normal(0, 0.05, (40, 128)).astype(np.float32)
    distances = np.linalg.norm(query[:, None] - train[None], axis=2)
    found = make_matcher(False, exact=True).match(query, train)
    assert [m.trainIdx for m in found] == distances.argmin(axis=1).tolist()


def test_cross_checked_recognition_still_finds_the_target(scene, frames):
    options = RecognitionOptions(cross_check=True)
    recognizer = TargetRecognizer(build_target("poster", scene.texture, scene.size_m[0]), options)
    result = recognizer.recognise_image(frames[5].images["cam0"], scene.cameras[0].K)
    assert result.recognised


def test_bars_above_the_fit_refuse_a_pose(scene, frames):
    target = build_target("poster", scene.texture, scene.size_m[0])
    K = scene.cameras[0].K
    strict = TargetRecognizer(target, RecognitionOptions(max_rms_px=0.05)).recognise_image(frames[0].images["cam0"], K)
    assert strict.status is RecognitionStatus.REPROJECTION_TOO_HIGH and strict.T_camera_target is None
    assert strict.rms_px > 0.05
    many = TargetRecognizer(target, RecognitionOptions(min_inliers=100000)).recognise_image(frames[0].images["cam0"], K)
    assert many.status is RecognitionStatus.TOO_FEW_MATCHES


@pytest.mark.parametrize("options", [{"ratio": 0.0}, {"min_inliers": 3}, {"max_rms_px": 0}, {"sigma_px": -1.0},
                                     {"confidence": 1.0}])
def test_bad_options_are_refused(options):
    with pytest.raises(ValueError):
        RecognitionOptions(**options)


@pytest.mark.parametrize("feature", ["orb", "sift"])
def test_the_box_is_found_in_the_cluttered_scene(feature):
    box, scene_image = box_images()
    target = build_target("box", box, 0.1, feature)
    result = TargetRecognizer(target).recognise_image(scene_image, intrinsics(512, 384, SCENE_FOV_DEG))
    assert result.recognised and result.inliers >= 30
    outline = box_outline(result.homography, box.shape)
    assert np.linalg.norm(outline[0] - HAND_CHECKED_TOP_LEFT) < 2.0
    assert np.linalg.norm(outline - OUTLINE, axis=1).max() < 6.0
