"""Rigid bodies of spheres found among measured 3D points, and their poses.

A body is (N, 3) float64 sphere centres in its own frame (N >= 3). The points are (M, 3) float64
sphere centres measured in the world frame, in no particular order, among them ghosts, other
bodies' spheres and stray markers. Matching runs in three steps:

1. ``body_candidates``: for one body, every assignment of spheres to points whose pairwise
   distances all agree with the body's to within ``distance_tolerance`` (an interpretation tree:
   spheres taken in order, each new one tried only on points at the right distance from every
   point already chosen; every branch of one depth, of every body matched together, grown at once
   from a table of which point pairs fit which sphere pairs). A body of four or more spheres may
   leave spheres unassigned (hidden), down to three seen; a three-sphere body needs all three. Each
   assignment is verified by a rigid fit (least squares, all bodies' assignments in one
   ``least_squares_transforms``): its residual RMS must be within ``within_gates``: ``gate_rms``, and on
   three spheres also ``three_turn_deg`` (in radians) times the triangle's ``width``, its least height
   (a wrong point turns a pose on three spheres the most and shows the least in its residual).
   Covariances are
   computed for the chosen fits only, in one ``pose_covariances``.
2. ``match_bodies``: one candidate (or none) per body, no point used by two bodies, chosen for the
   whole set at once among the candidates with at most one sphere hidden: the most bodies, then the
   most spheres, then the least total squared residual (a branch and bound over the bodies), so a
   body listed first never takes a point another body needs. Then, if a body of five spheres or
   more is still missing, the trees of every body are grown again among the points left, down to
   three spheres seen, and a body missing is given an assignment with two spheres hidden or more (a
   *sparse* candidate) where only an unambiguous one is found there (see below).
3. Each chosen body carries its ``RigidFit``: ``T_world_body``, residual RMS and, when point
   covariances are given, the pose covariance. Points no body took are listed as unassigned.

Three spheres match by chance more easily than four, so a sparse candidate must be unambiguous:

* its seen spheres are not nearly on one line: one lies ``sparse_width`` or more from the line through
  the two farthest apart (a thin triangle leaves the rotation about its long side loose);
* no other assignment of those trees holds all its points, unless on the same spheres of the same
  body: no other triangle of the body (its distances repeated within the tolerance), nor one of
  another body, fits those points;
* it is the body's only sparse candidate that fits there (bar those it extends), and no other body's
  sparse candidate taken there shares a point with it.

Where the points of a body's spheres are already known (labelled near a prediction), ``fit_labelled``
fits the bodies without a search, letting go of the worst sphere while a fit breaks its gate.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from services.estimation.bodies.fit_kernel import fit_bodies
from services.geometry.absolute_orientation import (
    COLLINEAR_TOLERANCE,
    RigidFit,
    least_squares_transforms,
    pose_covariances,
)
from services.geometry.shapes import check_shape

__all__ = [
    "DEFAULT_OPTIONS",
    "BodyMatch",
    "Candidate",
    "Matching",
    "MatchOptions",
    "body_candidates",
    "check_points",
    "fit_labelled",
    "match_bodies",
    "pairwise_distances",
    "width",
    "with_the_rest",
    "within_gates",
]


class MatchOptions(BaseModel):
    """How bodies are found among the points (see the module docstring)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    distance_tolerance: float = Field(default=0.003, gt=0, allow_inf_nan=False,
                                      description="sphere distance tolerance of matching, m: largest difference "
                                                  "between a measured and a body's pairwise distance")
    gate_rms: float = Field(default=0.001, gt=0, allow_inf_nan=False,
                            description="largest residual RMS of a body's fit, m: a few times the fits' RMS "
                                        "(0.1-0.3 mm), under what a wrong point within distance_tolerance gives")
    three_turn_deg: float = Field(default=1.0, gt=0, allow_inf_nan=False,
                                  description="largest turn, degrees, the residual of a fit on three spheres may "
                                              "allow: its RMS at most this angle times the triangle's width (a "
                                              "wrong point turns a pose on three spheres the most and shows the "
                                              "least in its residual)")
    allow_missing: bool = Field(default=True, description="a body of four or more spheres may be matched with "
                                                          "spheres hidden: one freely, more (down to three seen) "
                                                          "only where unambiguous")
    sparse_width: float = Field(default=0.015, gt=0, allow_inf_nan=False,
                                description="narrowest a body found with two spheres hidden or more may be, m: one "
                                            "seen sphere this far at least from the line through the two farthest "
                                            "apart")
    max_candidates: int = Field(default=32, ge=1, description="assignments with at most one sphere hidden kept per "
                                                              "body (the best: most spheres, then least residual) "
                                                              "for the global choice")


DEFAULT_OPTIONS = MatchOptions()


@dataclass(frozen=True)
class Candidate:
    """One verified assignment of a body: ``indices`` (N,) int64, the point index per sphere (-1: hidden),
    and the rigid fit over the assigned spheres."""

    indices: np.ndarray
    fit: RigidFit

    @property
    def used(self) -> np.ndarray:
        """(K,) int64 point indices this assignment takes."""
        return self.indices[self.indices >= 0]

    @property
    def squared_error(self) -> float:
        """Sum of squared residuals (m^2) of the fit."""
        return self.fit.residual_rms**2 * self.fit.count


@dataclass(frozen=True)
class BodyMatch:
    """A body found: ``name``, ``indices`` (N,) int64 point index per sphere (-1 where the sphere was not
    seen) and ``fit`` (``T_world_body``, residual RMS in metres, spheres used, optional 6x6 covariance)."""

    name: str
    indices: np.ndarray
    fit: RigidFit

    @property
    def spheres_used(self) -> int:
        return int(np.count_nonzero(self.indices >= 0))


@dataclass(frozen=True)
class Matching:
    """``bodies``: name -> BodyMatch for every body found (bodies not found are absent);
    ``unassigned``: (K,) int64 sorted indices of the points no body took."""

    bodies: dict[str, BodyMatch] = field(default_factory=dict)
    unassigned: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))


def with_the_rest(names: list[str], found: dict[str, BodyMatch], point_count: int,
                  search: Callable[[list[str], np.ndarray], Matching]) -> Matching:
    """The ``Matching`` of ``found`` (name -> BodyMatch, indices into ``point_count`` points) and of the bodies of
    ``names`` it lacks, looked for by ``search(those names, (K,) indices of the points no found body took)``,
    whose indices count among those K points; bodies in ``names`` order."""
    found = dict(found)
    taken = np.zeros(point_count, bool)
    for match in found.values():
        taken[match.indices[match.indices >= 0]] = True
    rest = [name for name in names if name not in found]
    free = np.flatnonzero(~taken)
    if rest and len(free):
        for name, match in search(rest, free).bodies.items():
            remapped = np.where(match.indices >= 0, free[np.maximum(match.indices, 0)], -1)
            found[name] = BodyMatch(name, remapped, match.fit)
            taken[remapped[remapped >= 0]] = True
    return Matching({name: found[name] for name in names if name in found}, np.flatnonzero(~taken).astype(np.int64))


def check_points(points: np.ndarray, name: str = "points") -> np.ndarray:
    """``points`` as an (M, 3) float64 array of finite values, else ValueError naming ``name``."""
    array = check_shape(points, "M,3", name, np.float64)
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{name} must be finite, got NaN or infinity")
    return array


def pairwise_distances(points: np.ndarray) -> np.ndarray:
    """(M, M) float64 Euclidean distances between the rows of (M, 3) ``points``."""
    difference = points[:, None, :] - points[None, :, :]
    return np.sqrt(np.sum(difference**2, axis=2))


def body_candidates(spheres: np.ndarray, points: np.ndarray, options: MatchOptions = DEFAULT_OPTIONS,
                    covariances: np.ndarray | None = None,
                    distances: np.ndarray | None = None) -> list[Candidate]:
    """Every verified assignment of one body's spheres to points, best first (most spheres, least residual).

    ``spheres``: (N, 3) float64, body frame, N >= 3; ``points``: (M, 3) float64, world frame;
    ``covariances``: (M, 3, 3) of the points (m^2) for the fits' covariances, or None; ``distances``:
    the points' (M, M) ``pairwise_distances`` when already known. At most ``options.max_candidates`` with one
    sphere hidden at most, then the sparse ones (two hidden or more) not ruled out as ambiguous by the points
    alone (module docstring).
    """
    points = check_points(points)
    distances = pairwise_distances(points) if distances is None else distances
    return (_candidates([spheres], points, options, covariances, distances, sparse=False)[0]
            + _candidates([spheres], points, options, covariances, distances, sparse=True)[0])


def _candidates(bodies: list[np.ndarray], points: np.ndarray, options: MatchOptions, covariances: np.ndarray | None,
                distances: np.ndarray, sparse: bool) -> list[list[Candidate]]:
    """Per body, best first, the verified assignments with one sphere hidden at most (at most ``max_candidates``),
    or with ``sparse`` those with two hidden or more that are unambiguous in the trees of all ``bodies`` (module
    docstring); every assignment's fit in one batched SVD."""
    bodies = [check_points(spheres, "spheres") for spheres in bodies]
    for spheres in bodies:
        if len(spheres) < 3:
            raise ValueError(f"a body needs at least 3 spheres, got {len(spheres)}")
    sizes = np.array([len(spheres) for spheres in bodies])
    widest = int(sizes.max())
    padded = np.zeros((len(bodies), widest, 3))
    for b, spheres in enumerate(bodies):
        padded[b, :len(spheres)] = spheres
    may_miss = (sizes - 3 if sparse else np.minimum(sizes - 3, 1)) * options.allow_missing
    # Every assignment of every body, padded to the widest body (padding unseen), body after body.
    owner, assignments = _assignments(padded, sizes.tolist(), distances, options.distance_tolerance,
                                      may_miss.tolist())
    by_body = np.argsort(owner, kind="stable")
    owner, assignments = owner[by_body], assignments[by_body]
    seen = assignments >= 0
    kept = ~_collinear(padded[owner], seen)
    if sparse:
        kept &= seen.sum(axis=1) <= sizes[owner] - 2
        rows = np.flatnonzero(kept)
        kept[rows] = ~_contested(owner, assignments, rows, len(points))
        rows = np.flatnonzero(kept)
        kept[rows] = width(padded[owner[rows]], seen[rows]) >= options.sparse_width
    owner, assignments, seen = owner[kept], assignments[kept], seen[kept]
    transforms, rms = least_squares_transforms(padded[owner], points[np.maximum(assignments, 0)], seen)
    used = seen.sum(axis=1)
    good = np.flatnonzero(within_gates(padded[owner], seen, rms, options))
    out = []
    for b, spheres in enumerate(bodies):
        mine = good[owner[good] == b]
        order = sorted(mine.tolist(), key=lambda k: (-int(used[k]), rms[k],
                                                     _tree_order(assignments[k], len(points))))
        order = order if sparse else order[:options.max_candidates]
        picked = [(spheres, assignments[k, :len(spheres)].copy()) for k in order]
        fits = [RigidFit(transforms[k], float(rms[k]), int(used[k])) for k in order]
        out.append([Candidate(indices, fit) for (_, indices), fit in
                    zip(picked, _with_covariances(picked, fits, covariances), strict=True)])
    return out


def within_gates(spheres: np.ndarray, seen: np.ndarray, rms: np.ndarray, options: MatchOptions) -> np.ndarray:
    """(A,) bool: whether each fit's residual ``rms`` (A,) m is within its gate: ``options.gate_rms``, and on three
    spheres ``options.three_turn_deg`` (as radians) times their ``width``.

    ``spheres``: (A, N, 3) float64, body frame; ``seen``: (A, N) bool, the spheres of each fit (three or more)."""
    within = rms <= options.gate_rms
    three = np.flatnonzero(within & (np.count_nonzero(seen, axis=1) == 3))
    if len(three):
        within[three] = rms[three] <= np.radians(options.three_turn_deg) * width(spheres[three], seen[three])
    return within


def _contested(owner: np.ndarray, assignments: np.ndarray, rows: np.ndarray, point_count: int) -> np.ndarray:
    """(R,) bool: whether another of the (A, N) ``assignments`` (of bodies ``owner`` (A,), -1: hidden) holds every
    point of assignment ``rows[r]`` but not each on the same sphere of the same body."""
    seen = assignments >= 0
    holds = np.zeros((len(assignments), point_count), np.int64)
    holds[np.nonzero(seen)[0], assignments[seen]] = 1
    outside = holds[rows].astype(np.float64) @ (1.0 - holds).T
    mine, other = np.nonzero(outside == 0)
    kin = (owner[rows[mine]] == owner[other]) & np.all(
        (assignments[other] == assignments[rows[mine]]) | ~seen[rows[mine]], axis=1)
    return np.bincount(mine[~kin], minlength=len(rows)) > 0


def width(spheres: np.ndarray, seen: np.ndarray) -> np.ndarray:
    """(A,) float64: the farthest any seen sphere lies from the line through the two seen spheres farthest apart,
    per row of (A, N, 3) ``spheres`` with (A, N) bool ``seen`` (at least two)."""
    if not len(spheres):
        return np.zeros(0)
    apart = np.where(seen[:, :, None] & seen[:, None, :],
                     np.linalg.norm(spheres[:, :, None] - spheres[:, None], axis=3), -1.0)
    first, second = np.unravel_index(np.argmax(apart.reshape(len(spheres), -1), axis=1), apart.shape[1:])
    rows = np.arange(len(spheres))
    origin = spheres[rows, first]
    direction = spheres[rows, second] - origin
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    offset = spheres - origin[:, None]
    across = offset - np.sum(offset * direction[:, None], axis=2, keepdims=True) * direction[:, None]
    return np.max(np.where(seen, np.linalg.norm(across, axis=2), 0.0), axis=1)


def _collinear(spheres: np.ndarray, seen: np.ndarray) -> np.ndarray:
    """(A,) bool: whether the spheres ``seen[a]`` ((A, N) bool) of (A, N, 3) ``spheres`` lie on one line
    (``fit_rigid`` refuses them: the rotation about that line is free)."""
    weight = seen[..., None].astype(np.float64)
    mean = (weight * spheres).sum(axis=1) / np.maximum(weight.sum(axis=1), 1.0)
    spread = np.linalg.svd(weight * (spheres - mean[:, None]), compute_uv=False)
    return spread[:, 1] <= COLLINEAR_TOLERANCE * np.maximum(spread[:, 0], 1e-300)


def _tree_order(indices: np.ndarray, point_count: int) -> tuple[int, ...]:
    """Rank of an assignment in the interpretation tree: spheres in turn, points ascending, hidden last."""
    return tuple(int(i) if i >= 0 else point_count for i in indices)


def _with_covariances(picked: list[tuple[np.ndarray, np.ndarray]], fits: list[RigidFit],
                      covariances: np.ndarray | None) -> list[RigidFit]:
    """``fits``, each of the assignment ``picked[k]`` = ``(spheres (N, 3), indices (N,))`` already solved, with
    its pose covariance from the points' ``covariances`` ((M, 3, 3) m^2), all in one batch; as they are
    without ``covariances``."""
    if covariances is None or not fits:
        return fits
    widest = max(len(spheres) for spheres, _ in picked)
    body = np.zeros((len(picked), widest, 3))
    sigma = np.zeros((len(picked), widest, 3, 3))
    used = np.zeros((len(picked), widest), bool)
    for row, (spheres, indices) in enumerate(picked):
        body[row, :len(spheres)], used[row, :len(spheres)] = spheres, indices >= 0
        sigma[row, :len(spheres)] = covariances[np.maximum(indices, 0)]
    found = pose_covariances(np.array([fit.T_world_body for fit in fits]), body, sigma, used)
    return [RigidFit(fit.T_world_body, fit.residual_rms, fit.count, covariance)
            for fit, covariance in zip(fits, found, strict=True)]


def _assignments(spheres: np.ndarray, sizes: list[int], point_distances: np.ndarray, tolerance: float,
                 may_miss: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """Every assignment of each body's spheres to distinct points (-1: hidden, at most ``may_miss[b]`` of body
    b) whose pairwise distances all agree with the body's within ``tolerance``: an interpretation tree grown
    sphere by sphere for all branches of all bodies at once; each branch carries, per sphere still to assign,
    the points it may still take (at first those with enough partners at the body's distances).

    ``spheres``: (B, N, 3) the bodies' spheres, body b's first ``sizes[b]`` rows; ``point_distances``: (M, M) m.
    Returns ``(owner (A,) int64, assignments (A, N) int64)``: each assignment's body and its point per sphere
    (-1 past the body's spheres); a body's assignments in the order of its own tree.
    """
    n = spheres.shape[1]
    present = np.arange(n) < np.array(sizes)[:, None]
    body_distances = np.where(present[:, :, None] & present[:, None, :],
                              np.sqrt(np.sum((spheres[:, :, None] - spheres[:, None]) ** 2, axis=3)), np.nan)
    # agree[b, k, s, p, q]: point q may be sphere k of body b when point p is its sphere s.
    agree = np.abs(point_distances[None, None, None] - body_distances[..., None, None]) <= tolerance
    # Point q can be sphere k only if, for all the other spheres but the hidden ones, some point lies at the
    # right distance from it: most points are ruled out for most spheres before the tree is grown.
    partners = agree.any(axis=3)
    partners[:, np.arange(n), np.arange(n)] = False
    spare = np.array(may_miss)
    possible = partners.sum(axis=2) >= (np.array(sizes) - 1 - spare)[:, None, None]
    unplaced = np.count_nonzero(present & ~possible.any(axis=2), axis=1)
    owner = np.flatnonzero(unplaced <= spare)
    partial = np.zeros((len(owner), 0), np.int64)
    possible = possible[owner]
    missing = np.zeros(len(owner), np.int64)
    for k in range(n):
        if not len(owner):
            break
        growing = present[owner, k]
        rows, columns = np.nonzero(possible[:, k] & growing[:, None])
        grown = possible[rows] & agree[owner[rows], :, k, columns]
        grown[np.arange(len(rows)), :, columns] = False
        hide = np.flatnonzero(growing & (missing < spare[owner]))
        done = np.flatnonzero(~growing)
        kept = np.concatenate([rows, hide, done])
        partial = np.hstack([partial[kept], np.concatenate([columns, np.full(len(kept) - len(rows), -1)])[:, None]])
        owner = owner[kept]
        missing = np.concatenate([missing[rows], missing[hide] + 1, missing[done]])
        possible = np.concatenate([grown, possible[hide], possible[done]])
    return owner, partial.reshape(len(owner), n)


def fit_labelled(bodies: Mapping[str, np.ndarray], points: np.ndarray, covariances: np.ndarray | None,
                 labels: Mapping[str, np.ndarray], options: MatchOptions, min_spheres: int) -> dict[str, BodyMatch]:
    """The bodies of ``labels`` fitted to the points their spheres are labelled with: name -> match, for those fitted.

    ``bodies``: name -> (N, 3) float64 sphere centres, body frame; ``points``: (M, 3) float64, world frame;
    ``covariances``: (M, 3, 3) m^2 or None; ``labels``: name -> (N,) int64 point index per sphere (-1: none).
    A body is fitted (least squares) while it has ``min_spheres`` labelled spheres not on one line; while its
    residual RMS is not ``within_gates``, the sphere whose absence leaves the best fit is let go (its index set
    to -1; with three, the first) and it is fitted again. The fits kept get their covariances
    (``absolute_orientation.pose_covariances``). Compiled: ``fit_kernel.fit_bodies``.
    """
    names = list(labels)
    if not names:
        return {}
    widest = max(len(bodies[name]) for name in names)
    spheres = np.zeros((len(names), widest, 3))
    padded = np.full((len(names), widest), -1, np.int64)
    for row, name in enumerate(names):
        spheres[row, :len(bodies[name])], padded[row, :len(bodies[name])] = bodies[name], labels[name]
    fitted, transforms, rms, indices, pose_sigma = fit_bodies(
        spheres, np.array([len(bodies[name]) for name in names]), padded, points, covariances, options.gate_rms,
        np.radians(options.three_turn_deg), min_spheres, COLLINEAR_TOLERANCE)
    found = {}
    for row in np.flatnonzero(fitted).tolist():
        name = names[row]
        kept = indices[row, :len(bodies[name])]
        found[name] = BodyMatch(name, kept, RigidFit(transforms[row], float(rms[row]), int(np.count_nonzero(kept >= 0)),
                                                     None if covariances is None else pose_sigma[row]))
    return found


def match_bodies(bodies: Mapping[str, np.ndarray], points_world: np.ndarray,
                 covariances: np.ndarray | None = None, options: MatchOptions = DEFAULT_OPTIONS) -> Matching:
    """Find the bodies among the points, each point used by at most one body.

    ``bodies``: name -> (N, 3) float64 sphere centres, body frame; ``points_world``: (M, 3) float64,
    world frame; ``covariances``: (M, 3, 3) float64 point covariances (m^2), or None (then the fits
    carry no covariance). The choice maximises, over all bodies together, the number of bodies found with
    one sphere hidden at most, then the number of spheres used, then minimises the total squared residual;
    then the bodies missing are looked for from three spheres or more among the points left, unambiguous
    only (module docstring).
    """
    points = check_points(points_world, "points_world")
    if covariances is not None:
        covariances = check_shape(covariances, f"{len(points)},3,3", "covariances", np.float64)
    distances = pairwise_distances(points)
    names = list(bodies)
    spheres = [bodies[name] for name in names]
    choice = _best_choice(_candidates(spheres, points, options, None, distances, sparse=False), len(points)) \
        if names else []
    taken = np.zeros(len(points), bool)
    for candidate in choice:
        if candidate is not None:
            taken[candidate.used] = True
    free = np.flatnonzero(~taken)
    if options.allow_missing and any(c is None and len(s) >= 5 for c, s in zip(choice, spheres, strict=True)):
        choice = _sparse_choice(_candidates(spheres, points[free], options, None, distances[np.ix_(free, free)],
                                            sparse=True), choice, free)
    chosen = [(names[k], c) for k, c in enumerate(choice) if c is not None]
    fits = _with_covariances([(np.asarray(bodies[name], np.float64), c.indices) for name, c in chosen],
                             [c.fit for _, c in chosen], covariances)
    matched = {name: BodyMatch(name, c.indices, fit) for (name, c), fit in zip(chosen, fits, strict=True)}
    taken[:] = False
    for match in matched.values():
        taken[match.indices[match.indices >= 0]] = True
    return Matching(matched, np.flatnonzero(~taken).astype(np.int64))


def _sparse_choice(candidates: list[list[Candidate]], choice: list[Candidate | None],
                   free: np.ndarray) -> list[Candidate | None]:
    """``choice`` (one candidate or None per body) with each body it lacks given its one sparse candidate among the
    ``free`` points ((K,) indices; ``candidates`` index them), when it has exactly one bar those it extends, and
    when no other body so given shares a point with it (module docstring); their indices those of all points."""
    given: dict[int, Candidate] = {}
    for k, options in enumerate(candidates):
        if choice[k] is not None or not options:
            continue
        indices = np.array([c.indices for c in options])
        # extends[i, j]: candidate i gives every point of candidate j to the same sphere.
        extends = np.all((indices[:, None] == indices[None]) | (indices[None] < 0), axis=2)
        widest = np.flatnonzero(np.count_nonzero(extends, axis=0) == 1)
        if len(widest) == 1:
            only = options[int(widest[0])]
            given[k] = Candidate(np.where(only.indices >= 0, free[np.maximum(only.indices, 0)], -1), only.fit)
    clash = {k for k, mine in given.items() for j, other in given.items()
             if j != k and np.intersect1d(mine.used, other.used).size}
    return [c if c is not None or k in clash else given.get(k) for k, c in enumerate(choice)]


Score = tuple[int, int, float]
"""(bodies found, spheres used, minus the total squared residual): larger is better."""


def _best_choice(candidates: list[list[Candidate]], point_count: int) -> list[Candidate | None]:
    """One candidate or None per body, disjoint in points, with the largest ``Score`` (branch and bound)."""
    # What the bodies from k on could add at best: every one found, each with its best candidate.
    bodies_left = _suffix_sums([1 if c else 0 for c in candidates])
    spheres_left = _suffix_sums([max((x.fit.count for x in c), default=0) for c in candidates])
    error_left = _suffix_sums([min((x.squared_error for x in c), default=0.0) for c in candidates])
    best_score: Score = (-1, -1, -np.inf)
    best_choice: list[Candidate | None] = []
    chosen: list[Candidate | None] = []
    used = np.zeros(point_count, bool)

    def search(k: int, found: int, spheres: int, error: float) -> None:
        nonlocal best_score, best_choice
        bound = (found + bodies_left[k], spheres + spheres_left[k], -(error + error_left[k]))
        if bound <= best_score:
            return
        if k == len(candidates):
            best_score, best_choice = (found, spheres, -error), list(chosen)
            return
        for candidate in candidates[k]:
            taken = candidate.used
            if used[taken].any():
                continue
            used[taken] = True
            chosen.append(candidate)
            search(k + 1, found + 1, spheres + candidate.fit.count, error + candidate.squared_error)
            chosen.pop()
            used[taken] = False
        chosen.append(None)
        search(k + 1, found, spheres, error)
        chosen.pop()

    search(0, 0, 0, 0.0)
    return best_choice


def _suffix_sums(values: list) -> list:
    """``[sum(values[k:]) for k in 0..len(values)]`` (the last is 0)."""
    return [sum(values[k:]) for k in range(len(values) + 1)]
