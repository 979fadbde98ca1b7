"""Bodies followed over instants: matching near predictions, the fall back to signatures, one instant bridged."""

import numpy as np

from protocol.message import Header
from protocol.tracking_state import TrackingState
from services.convert import matrix_from_transform
from services.estimation.bodies.node import Params, predicted_poses
from services.estimation.bodies.rigid import match_bodies
from services.estimation.bodies.tracking import BodyTracker, TrackingOptions, match_with_prediction
from services.geometry.evaluation import pose_error
from services.geometry.rotation import matrix_from_rotvec
from services.geometry.se3 import make_transform, transform_points
from services.launcher.tracker import Tracker
from services.synthetic.ir_rig import LAYOUTS, IrRigOptions, IrRigScene

NOISE_M = 0.0002
GHOSTS = 10
VOLUME = (np.array([-0.9, -0.5, 1.6]), np.array([0.9, 0.7, 2.8]))
SCENE = IrRigScene(IrRigOptions(body_count=len(LAYOUTS), width=64, height=64))


def stamp(index: int) -> int:
    return round(SCENE.time_s(index) * 1e9)


def instant(index: int, rng: np.random.Generator, without: frozenset[str] = frozenset(),
            ghosts: int = GHOSTS) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Shuffled noisy sphere points of the scene's bodies at ``index`` (less ``without``) among ghosts, and
    name -> (N,) index of each sphere's point."""
    poses = SCENE.body_poses(index)
    names = [name for name in LAYOUTS if name not in without]
    spheres = [transform_points(poses[name], LAYOUTS[name]) for name in names]
    points = np.concatenate([*spheres, rng.uniform(*VOLUME, (ghosts, 3))])
    points += rng.normal(0.0, NOISE_M, points.shape)
    order = rng.permutation(len(points))
    where = np.argsort(order)
    first = np.cumsum([0] + [len(s) for s in spheres])
    return points[order], {name: where[first[k]:first[k + 1]] for k, name in enumerate(names)}


def test_matching_near_predictions_takes_the_assignment_signature_matching_takes():
    rng = np.random.default_rng(0)
    tracker = BodyTracker(LAYOUTS)
    predicted = 0
    for index in range(0, 90, 2):
        points, truth = instant(index, rng)
        predicted += all(model.predict(stamp(index)) is not None for model in tracker.models.values())
        tracked = tracker.step(stamp(index), points)
        searched = match_bodies(LAYOUTS, points)
        assert set(tracked.matching.bodies) == set(searched.bodies) == set(LAYOUTS)
        for name, match in tracked.matching.bodies.items():
            assert np.array_equal(match.indices, searched.bodies[name].indices)
            assert np.array_equal(match.indices, truth[name])
        assert np.array_equal(tracked.matching.unassigned, searched.unassigned)
    assert predicted == 45 - 2  # from the third instant on, every body was looked for near its prediction


def test_a_prediction_resolves_what_distance_signatures_cannot():
    """The tool lacks a sphere, and ghosts happen to repeat its three other spheres exactly elsewhere:
    by distances alone the ghosts fit better (no noise), near the prediction only the tool's spheres lie."""
    rng = np.random.default_rng(1)
    T_tool = SCENE.body_poses(40)["tool"]
    seen = transform_points(T_tool, LAYOUTS["tool"][:3]) + rng.normal(0.0, NOISE_M, (3, 3))
    T_elsewhere = make_transform(matrix_from_rotvec(np.array([0.4, -1.1, 0.3])), np.array([0.5, 0.3, 2.6]))
    ghosts = np.concatenate([transform_points(T_elsewhere, LAYOUTS["tool"][:3]), rng.uniform(*VOLUME, (6, 3))])
    points = np.concatenate([seen, ghosts])
    bodies = {"tool": LAYOUTS["tool"]}
    searched = match_bodies(bodies, points)
    assert list(searched.bodies["tool"].indices) == [3, 4, 5, -1]  # the ghosts
    error = make_transform(matrix_from_rotvec(np.array([0.01, 0.0, -0.01])), np.array([0.003, -0.002, 0.001]))
    predicted = T_tool @ error
    matched = match_with_prediction(bodies, points, {"tool": predicted})
    assert list(matched.bodies["tool"].indices) == [0, 1, 2, -1]
    assert pose_error(matched.bodies["tool"].fit.T_world_body, T_tool)[1] < 0.001
    assert list(matched.unassigned) == list(range(3, len(points)))


def test_a_prediction_that_finds_nothing_falls_back_to_signatures_and_no_point_serves_two_bodies():
    rng = np.random.default_rng(2)
    points, truth = instant(20, rng)
    poses = SCENE.body_poses(20)
    # the wand predicted 10 cm off (nothing within the gate), the tool and head predicted onto each other
    predictions = {"wand": poses["wand"] @ make_transform(np.eye(3), np.array([0.1, 0.0, 0.0])),
                   "tool": poses["head"], "head": poses["head"], "glove": poses["glove"]}
    matched = match_with_prediction(LAYOUTS, points, predictions)
    assert set(matched.bodies) == set(LAYOUTS)
    for name, match in matched.bodies.items():
        assert np.array_equal(match.indices, truth[name]), name
    used = np.concatenate([m.indices[m.indices >= 0] for m in matched.bodies.values()])
    assert len(used) == len(set(used.tolist()))


def test_one_missing_instant_is_bridged_near_the_truth_then_the_body_is_lost():
    rng = np.random.default_rng(3)
    tracker = BodyTracker(LAYOUTS, tracking=TrackingOptions())
    for index in range(10, 14):
        assert set(tracker.step(stamp(index), instant(index, rng)[0]).matching.bodies) == set(LAYOUTS)
    bridged = tracker.step(stamp(14), instant(14, rng, frozenset({"tool"}))[0])
    assert "tool" not in bridged.matching.bodies and list(bridged.predicted) == ["tool"]
    rotation, translation = pose_error(bridged.predicted["tool"].T_world_body, SCENE.body_poses(14)["tool"])
    assert translation < 0.002 and np.degrees(rotation) < 0.5
    gone = tracker.step(stamp(15), instant(15, rng, frozenset({"tool"}))[0])
    assert "tool" not in gone.matching.bodies and gone.predicted == {}
    assert "tool" not in tracker.bridged  # its track ends here: the node publishes it lost
    back = tracker.step(stamp(16), instant(16, rng)[0])
    assert set(back.matching.bodies) == set(LAYOUTS) and back.predicted == {}
    # time going back (a recording played again) starts every body afresh, nothing predicted
    again = tracker.step(stamp(10), instant(10, rng, frozenset({"tool"}))[0])
    assert again.predicted == {} and not any(model.ready for model in tracker.models.values())
    # a body seen once only has no motion yet: missing, it is lost at once
    fresh = BodyTracker(LAYOUTS)
    fresh.step(stamp(30), instant(30, rng)[0])
    assert fresh.step(stamp(31), instant(31, rng, frozenset({"wand"}))[0]).predicted == {}


def test_a_bridged_body_is_published_as_predicted_with_its_grown_covariance():
    rng = np.random.default_rng(4)
    tracker = BodyTracker(LAYOUTS)
    for index in (0, 1):
        points, _ = instant(index, rng)
        tracker.step(stamp(index), points, np.tile(np.eye(3) * NOISE_M**2, (len(points), 1, 1)))
    points, _ = instant(2, rng, frozenset({"head"}))
    tracked = tracker.step(stamp(2), points, np.tile(np.eye(3) * NOISE_M**2, (len(points), 1, 1)))
    header = Header(stamp_ns=stamp(2), frame_id="world", seq=2)
    (pose,) = predicted_poses(header, tracked.predicted)
    assert pose.state is TrackingState.PREDICTED and pose.child_frame_id == "body/head"
    assert pose.quality.inliers == 0 and pose.covariance is not None
    assert np.allclose(matrix_from_transform(pose.transform), tracked.predicted["head"].T_world_body)
    fitted = tracker.models["head"]._samples[-1].covariance
    assert np.trace(np.reshape(pose.covariance, (6, 6))) > 5 * np.trace(fitted)


def test_prediction_is_on_by_default_and_a_flag_of_the_stereo_tracker():
    assert Params().predict is True
    assert Params(predict=False).predict is False
    options = {flag.option for flag in Tracker.load("stereo").flags({})}
    assert {"--predict", "--predict-gate", "--predict-gate-px", "--predict-gap-s"} <= options
    tracking = Params(predict_gate=0.02, predict_gate_px=2.5, predict_gap_s=0.25).tracking
    assert tracking.gate == 0.02 and tracking.gate_px == 2.5 and tracking.motion.max_gap_ns == 250_000_000
