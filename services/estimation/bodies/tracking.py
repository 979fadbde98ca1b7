"""Rigid bodies followed from instant to instant: matching near predicted poses, and one missing instant bridged.

``match_with_prediction`` finds the bodies among an instant's points as ``rigid_bodies.match_bodies``
does, but a body with a predicted pose is looked for first where its spheres should be:

1. every predicted body's spheres are placed at their predicted world positions, and all of them
   together are assigned one-to-one to the points (least total distance, each pair closer than
   ``gate`` metres, ``correspondence.gated_assignment``), so no point goes to two bodies;
2. each predicted body with at least ``min_spheres`` spheres assigned is fitted (``rigid.fit_labelled``,
   all of them in one batch); while its residual RMS exceeds its gate (``rigid.within_gates``) and
   spheres remain above ``min_spheres``, the sphere whose absence leaves the best fit is let go and the
   body fitted again;
3. the bodies without a prediction, or whose predicted assignment failed, are matched by their
   distance signatures (``match_bodies``) among the points the others left.

``BodyTracker`` follows the bodies instant after instant, one ``motion.ConstantVelocity`` per body fed
with the fits: ``forecast`` gives each body's predicted pose at an instant, ``record`` takes in the
bodies found there (by ``match_with_prediction`` on points, ``step``, or in the images,
``labelled.track_blobs``) and bridges: a body published at the previous instant (found, or bridged less
than ``bridge`` times in a row) and not found now is given its predicted pose and covariance, to be
published with state ``predicted``; missing once more, it is left out (its track reports it lost).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from services.estimation.bodies.correspondence import gated_assignment
from services.estimation.bodies.rigid import (
    DEFAULT_OPTIONS,
    BodyMatch,
    Matching,
    MatchOptions,
    check_points,
    fit_labelled,
    match_bodies,
    with_the_rest,
)
from services.estimation.motion import DEFAULT_MOTION, ConstantVelocity, MotionOptions, Prediction
from services.geometry.se3 import transform_points
from services.geometry.shapes import check_shape

__all__ = ["DEFAULT_TRACKING", "BodyTracker", "Tracked", "TrackingOptions", "match_with_prediction"]


class TrackingOptions(BaseModel):
    """How bodies are followed from instant to instant (see the module docstring)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    gate: float = Field(default=0.015, gt=0, allow_inf_nan=False,
                        description="farthest a point may lie from a sphere's predicted position, m")
    gate_px: float = Field(default=3.0, gt=0, allow_inf_nan=False,
                           description="farthest a blob may lie from a sphere's predicted image, px")
    min_spheres: int = Field(default=3, ge=3, description="fewest spheres a predicted body is fitted with")
    bridge: int = Field(default=1, ge=0, description="instants in a row a body missing is given its predicted pose")
    motion: MotionOptions = Field(default=DEFAULT_MOTION, description="the constant-velocity model's options")


DEFAULT_TRACKING = TrackingOptions()


def match_with_prediction(bodies: Mapping[str, np.ndarray], points_world: np.ndarray,
                          predictions: Mapping[str, np.ndarray], covariances: np.ndarray | None = None,
                          options: MatchOptions = DEFAULT_OPTIONS,
                          tracking: TrackingOptions = DEFAULT_TRACKING) -> Matching:
    """Find the bodies among the points, the predicted ones near their predictions (see the module docstring).

    ``bodies``: name -> (N, 3) float64 sphere centres, body frame; ``points_world``: (M, 3) float64, world
    frame; ``predictions``: name -> (4, 4) predicted ``T_world_body`` (bodies absent have none);
    ``covariances``: (M, 3, 3) float64 point covariances (m^2) or None. Each point goes to one body at most.
    """
    points = check_points(points_world, "points_world")
    if covariances is not None:
        covariances = check_shape(covariances, f"{len(points)},3,3", "covariances", np.float64)
    names = list(bodies)
    predicted = [name for name in names if name in predictions]
    found: dict[str, BodyMatch] = {}
    if predicted and len(points):
        expected = np.concatenate([transform_points(predictions[name], bodies[name]) for name in predicted])
        owner = np.concatenate([np.full(len(bodies[name]), k) for k, name in enumerate(predicted)])
        first = np.cumsum([0] + [len(bodies[name]) for name in predicted])
        cost = np.linalg.norm(expected[:, None, :] - points[None, :, :], axis=2)
        indices = [np.full(len(bodies[name]), -1, np.int64) for name in predicted]
        for row, column in gated_assignment(cost, tracking.gate):
            k = owner[row]
            indices[k][row - first[k]] = column
        found = fit_labelled(bodies, points, covariances, dict(zip(predicted, indices, strict=True)),
                             options, tracking.min_spheres)
    return with_the_rest(names, found, len(points), lambda rest, free: match_bodies(
        {name: bodies[name] for name in rest}, points[free], None if covariances is None else covariances[free],
        options))


@dataclass(frozen=True)
class Tracked:
    """One instant: ``matching`` (the bodies found, as ``match_bodies`` gives them) and ``predicted``: name ->
    ``Prediction`` for each body bridged at this instant (not found, given its predicted pose)."""

    matching: Matching
    predicted: dict[str, Prediction] = field(default_factory=dict)


class BodyTracker:
    """The bodies followed over a sequence of instants (``step`` per instant, stamps increasing)."""

    def __init__(self, bodies: Mapping[str, np.ndarray], options: MatchOptions = DEFAULT_OPTIONS,
                 tracking: TrackingOptions = DEFAULT_TRACKING):
        self.bodies = dict(bodies)
        self.options = options
        self.tracking = tracking
        self.models = {name: ConstantVelocity(tracking.motion) for name in self.bodies}
        self.bridged: dict[str, int] = {}
        """Bodies published at the previous instant -> how many instants in a row they were bridged."""
        self.stamp_ns: int | None = None

    def forecast(self, stamp_ns: int) -> dict[str, Prediction]:
        """Name -> predicted pose at ``stamp_ns`` of each body whose motion is known. A ``stamp_ns`` not after
        the previous instant's (a recording played again from its start) starts every body afresh."""
        if self.stamp_ns is not None and stamp_ns <= self.stamp_ns:
            for model in self.models.values():
                model.reset()
            self.bridged = {}
        self.stamp_ns = stamp_ns
        return {name: forecast for name, model in self.models.items()
                if (forecast := model.predict(stamp_ns)) is not None}

    def record(self, stamp_ns: int, matching: Matching, forecasts: Mapping[str, Prediction]) -> Tracked:
        """Take in the bodies found at ``stamp_ns`` (``matching``; ``forecasts`` as ``forecast`` gave them):
        bridge those missing (``bridge``) and update the motion of those found (``learn``)."""
        tracked = self.bridge(matching, forecasts)
        self.learn(stamp_ns, matching)
        return tracked

    def bridge(self, matching: Matching, forecasts: Mapping[str, Prediction]) -> Tracked:
        """The bodies found (``matching``) and those missing from it given their forecasts, while they may still
        be bridged; the motions are left as they were (``learn`` takes the fits in)."""
        bridged: dict[str, int] = {name: 0 for name in matching.bodies}
        predicted: dict[str, Prediction] = {}
        for name, count in self.bridged.items():
            if name not in bridged and count < self.tracking.bridge and name in forecasts:
                predicted[name] = forecasts[name]
                bridged[name] = count + 1
        self.bridged = bridged
        return Tracked(matching, predicted)

    def learn(self, stamp_ns: int, matching: Matching) -> None:
        """Each body found at ``stamp_ns`` (``matching``) into its motion, for the next instant's forecast."""
        for name, match in matching.bodies.items():
            self.models[name].update(stamp_ns, match.fit.T_world_body, match.fit.covariance)

    def step(self, stamp_ns: int, points_world: np.ndarray, covariances: np.ndarray | None = None) -> Tracked:
        """One instant of points: ``forecast``, the bodies matched among the (M, 3) ``points_world`` (with (M, 3, 3)
        ``covariances`` or None) near their predictions (``match_with_prediction``), then ``record``."""
        forecasts = self.forecast(stamp_ns)
        points = check_points(points_world, "points_world")
        matching = Matching() if len(points) == 0 else match_with_prediction(
            self.bodies, points, {name: f.T_world_body for name, f in forecasts.items()}, covariances, self.options,
            self.tracking)
        return self.record(stamp_ns, matching, forecasts)
