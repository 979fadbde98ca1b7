"""Marker pose accuracy against the ground truth of the synthetic ``markers`` scene (640x480,
markers spanning 5-30 % of the image width), ours side by side with OpenCV alone.

Requirement: median rotation error <= 0.5 deg and median translation error <= 1 % of the
distance, the LM refinement strictly better than the raw homography pose, and on the same
corners the published single-marker poses at least as accurate as OpenCV alone (ArucoDetector
subpixel corners + solvePnP IPPE_SQUARE per marker). The board's pose is held to within
``SAME_OPTIMUM`` of OpenCV's (cv2.solvePnP's iterative method on all its corners), not to at least
as accurate: both minimise the same reprojection error and stop at the same optimum, apart by the
iterations' stopping rules (ours 0.05 % and 0.13 % above OpenCV's median rotation error on the
projected and the rendered views, translation the same to 0.001 %).

* Rendered frames, ArucoDetector corners: the thresholds and the comparison with OpenCV hold
  for single markers and the board. ArucoDetector's corners sit slightly inside the true ones,
  so every estimator places the markers slightly too far, and that bias sets the median
  translation error of all of them (the raw homography's happens to land lower, at a far larger
  spread): there the refinement beats the homography in rotation and in the translation
  error's spread (p90), and its range bias is the detector's.
* Exact corners + 0.5 px Gaussian noise per axis: the translation threshold and every
  comparison hold for single markers, but no estimator can reach 0.5 deg on one marker of
  this size: the Cramér-Rao bound (the covariance of ``refine.pose_covariance`` at the true
  pose) puts the median RMS rotation error well above it, and ours sits at that bound. The 0.5 deg
  is held on the board's pose (its 6 markers at once) with the same noise.

* Rendered frames, corners from ``MarkerDetector``'s default refinement (``lines``: lines
  fitted to each side's edge points): no inward bias (mean offset along the inward normals
  within 0.02 px, where ``subpix`` corners sit over 0.1 px inside), median corner error under
  0.05 px and under half of ``subpix``'s, and the poses at least as accurate as from ``subpix``
  corners in rotation and translation, the median translation error under 0.1 % of the
  distance and the range bias under 0.05 %.

``python -m tests.accuracy.report`` prints the figures (docs/benchmarks.md has them).
"""

import numpy as np
import pytest

from services.detection.markers.detector import DEFAULT_REFINEMENT
from services.estimation.markers.map import marker_corners
from services.geometry.camera import project_points
from services.geometry.refine import pose_covariance, residuals_and_jacobian
from services.geometry.se3 import transform_points
from services.synthetic import make_scene
from tests.accuracy.report import (
    NOISE_PX,
    WIDTH_RANGE,
    corner_errors,
    detected_views,
    evaluate,
    evaluate_board,
    projected_views,
    rendered_images,
)

pytestmark = pytest.mark.slow

MAX_ROTATION_DEG = 0.5
MAX_TRANSLATION_PCT = 1.0
SAME_OPTIMUM = 1.01
"""A board's median errors over OpenCV's at most: the same optimum, reached to within 1 %."""


@pytest.fixture(scope="module")
def scene():
    return make_scene("markers")


@pytest.fixture(scope="module")
def projected(scene):
    frames = projected_views(scene)
    return frames, evaluate(frames, scene.cameras[0].K, scene.marker_length), evaluate_board(frames, scene)


@pytest.fixture(scope="module")
def images(scene):
    return rendered_images(scene)


@pytest.fixture(scope="module")
def rendered(scene, images):
    frames = detected_views(scene, images=images)
    return frames, evaluate(frames, scene.cameras[0].K, scene.marker_length), evaluate_board(frames, scene)


@pytest.fixture(scope="module")
def rendered_default(scene, images):
    frames = detected_views(scene, refinement=DEFAULT_REFINEMENT, images=images)
    return frames, evaluate(frames, scene.cameras[0].K, scene.marker_length), evaluate_board(frames, scene)


def median(errors: dict[str, np.ndarray], key: str) -> float:
    assert np.all(np.isfinite(errors[key])), "an estimator gave no pose"
    return float(np.median(errors[key]))


def p90(errors: dict[str, np.ndarray], key: str) -> float:
    return float(np.percentile(errors[key], 90))


def assert_at_least_as_accurate(ours: dict[str, np.ndarray], theirs: dict[str, np.ndarray]) -> None:
    for key in ("rotation_deg", "translation_pct"):
        assert median(ours, key) <= median(theirs, key), key
    assert p90(ours, "rotation_deg") <= p90(theirs, "rotation_deg")


def assert_refinement_beats_the_homography(errors: dict[str, dict[str, np.ndarray]]) -> None:
    for key in ("rotation_deg", "translation_pct"):
        assert median(errors["lm"], key) < median(errors["homography"], key), key


def test_projected_views_cover_the_size_range(scene, projected):
    frames, _, _ = projected
    views = [view for frame in frames for view in frame.views]
    spans = [np.ptp(view.corners[:, 0]) / scene.cameras[0].width for view in views]
    assert len(views) >= 500
    assert min(spans) < 0.08 and max(spans) > 0.2 and WIDTH_RANGE[0] - 0.01 < min(spans) < max(spans) < 0.31


def test_projected_single_markers(scene, projected):
    frames, errors, _ = projected
    ours = errors["ours"]
    assert median(ours, "translation_pct") <= MAX_TRANSLATION_PCT
    assert_refinement_beats_the_homography(errors)
    assert_at_least_as_accurate(ours, errors["opencv"])
    K, length = scene.cameras[0].K, scene.marker_length
    bound_deg = []
    for view in (view for frame in frames for view in frame.views):
        _, J = residuals_and_jacobian(view.T_cam_marker, marker_corners(length), view.corners, K)
        bound_deg.append(np.degrees(np.sqrt(np.trace(pose_covariance(J, NOISE_PX)[3:, 3:]))))
    print(f"\nrotation error median {median(ours, 'rotation_deg'):.2f} deg, Cramér-Rao bound median "
          f"{np.median(bound_deg):.2f} deg")
    assert median(ours, "rotation_deg") <= np.median(bound_deg)


def test_projected_board(projected):
    _, _, errors = projected
    ours = errors["ours"]
    assert median(ours, "rotation_deg") <= MAX_ROTATION_DEG
    assert median(ours, "translation_pct") <= MAX_TRANSLATION_PCT
    for key in ("rotation_deg", "translation_pct"):
        assert median(ours, key) <= SAME_OPTIMUM * median(errors["opencv"], key), key
        assert median(ours, key) < median(errors["ippe"], key), key


def test_rendered_single_markers(scene, rendered):
    frames, errors, _ = rendered
    ours = errors["ours"]
    assert len(ours["rotation_deg"]) >= 300
    assert median(ours, "rotation_deg") <= MAX_ROTATION_DEG
    assert median(ours, "translation_pct") <= MAX_TRANSLATION_PCT
    assert_at_least_as_accurate(ours, errors["opencv"])
    lm, homography = errors["lm"], errors["homography"]
    assert median(lm, "rotation_deg") < median(homography, "rotation_deg")
    assert p90(lm, "translation_pct") < p90(homography, "translation_pct")
    K = scene.cameras[0].K
    shrink = []
    for view in (view for frame in frames for view in frame.views):
        exact = project_points(transform_points(view.T_cam_marker, marker_corners(scene.marker_length)), K)
        centre = exact.mean(axis=0)
        shrink.append(100 * (1 - np.mean(np.linalg.norm(view.corners - centre, axis=1) /
                                         np.linalg.norm(exact - centre, axis=1))))
    assert 0.3 < np.median(shrink) < 0.8
    assert median(lm, "range_pct") == pytest.approx(np.median(shrink), abs=0.1)


def test_rendered_board(rendered):
    _, _, errors = rendered
    ours = errors["ours"]
    assert median(ours, "rotation_deg") <= MAX_ROTATION_DEG
    assert median(ours, "translation_pct") <= MAX_TRANSLATION_PCT
    for key in ("rotation_deg", "translation_pct"):
        assert median(ours, key) <= SAME_OPTIMUM * median(errors["opencv"], key), key


def test_default_refinement_corners_are_unbiased(scene, rendered, rendered_default):
    K, length = scene.cameras[0].K, scene.marker_length
    error, inward = corner_errors(rendered_default[0], length, K)
    subpix_error, subpix_inward = corner_errors(rendered[0], length, K)
    assert len(error) == len(subpix_error) >= 1200
    assert abs(np.mean(inward)) < 0.02 and np.mean(subpix_inward) > 0.1
    assert np.median(error) < 0.05 and np.median(error) < 0.5 * np.median(subpix_error)


def test_default_refinement_poses_at_least_as_accurate_as_subpix(rendered, rendered_default):
    for index in (1, 2):
        ours, theirs = rendered_default[index]["ours"], rendered[index]["ours"]
        for key in ("rotation_deg", "translation_pct"):
            assert median(ours, key) <= median(theirs, key), (index, key)
    single = rendered_default[1]["ours"]
    assert median(single, "translation_pct") < 0.1
    assert abs(np.median(single["range_pct"])) < 0.05
