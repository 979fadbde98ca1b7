"""Where the stereo tracker loses a body, frame by frame, on the hard ``ir_rig`` scene.

The hard scene (``HARD``): three 640x480 cameras, each with its own distortion, on an arc around the
volume at different distances (``layout=arc``); the ``tool`` (4 spheres) and the ``head`` (5), spheres
of 15 mm diameter; 120 frames a second; a sphere hidden from one camera in a quarter of the half-second
windows (the scene's default occlusions); two stray reflections, real 3D points every camera sees, lit
for a while near a body (``strays=2``); the bodies turning ``SPIN`` times as far and as fast as the default
scene's (``spin``), so two spheres of a body come close, or merge into one blob, in some views. ``CONDITIONS``
switches each of the three hard conditions on alone over the ``BASE`` scene (the bar, no stray, the
default spin).

The tracker runs as ``artrack run stereo`` runs it: the blobs node's default detector per camera, then
the rigid_bodies node's default settings (``node.Params``: prediction on) through ``node.BodiesPerSet``,
each set stamped with the scene's time. Each body in each frame is then classified:

* not trackable: fewer than 3 of its spheres are seen (in front of the camera, inside the image, not
  hidden) by 2 cameras or more; left out of the tracked fraction;
* tracked: a tracking pose within ``GHOST_MM`` and ``GHOST_DEG`` of the truth (its errors kept);
* ghost: a tracking pose farther than that, or a tracking pose where the body is not trackable;
* lost: trackable and no tracking pose (a ``predicted`` pose bridging one set is counted apart).

A lost frame gets one cause, the first that applies (``CAUSES``): ``merged`` (in some camera two of the
spheres, its own or another body's, lie closer than their image radii plus ``MERGE_MARGIN_PX``: their
blobs run into one), ``hidden`` (one of its spheres is hidden from a camera), ``stray`` (a stray within
``STRAY_PX`` of one of its spheres' images in some camera, or within the body's size of its centre in
3D), ``edge`` (one of its spheres' images within ``EDGE_PX`` of the image border, where the distortion
is largest and blobs are clipped), else ``unknown``. It also gets the tracker's step where it was lost
(``STAGES``), the first that fails:

* ``blobs``: fewer than 3 spheres have a clean (unflagged) blob, or a part of a split blob, within ``BLOB_PX``
  of their image in 2 cameras or more (merged, occluded or clipped blobs are not triangulated);
* ``labels``: the body was predicted but fewer than 3 of its spheres were labelled in 2 cameras or more
  (``labelled.label_blobs``: a view within the gate of two predicted spheres is doubtful and dropped;
  ``labelled.label_parts``: a split blob's parts go to the two predicted spheres inside it)
  and the full path did not make up for it (fewer than 3 sphere points);
* ``pairing``: fewer than 3 of its spheres became points (within ``POINT_MM`` of their true centre), and a
  point far from every sphere (a ghost) was made of one of their clean blobs: correspondence paired the
  blobs of two different spheres, and the right partners were left without theirs;
* ``points``: fewer than 3 of its spheres became points otherwise: correspondence left them unpaired (an
  ambiguous pair, a view dropped) or triangulation refused them;
* ``residual``: 3 or more sphere points, but their fit's RMS is above the node's gate (``rigid.within_gates``:
  ``gate_rms``, tighter on three spheres);
* ``search``: 3 or more sphere points that fit, but the body was not predicted (not found yet, or lost for
  longer than ``predict_gap_s``) and has fewer than all its spheres but one: the search by distances
  (``rigid.match_bodies``) takes a body with two spheres hidden or more only where unambiguous;
* ``matching``: 3 or more sphere points that fit, and still no pose (taken by another body, or no
  assignment found among the points).

``PYTHONPATH=. python -m tests.accuracy.stereo_losses [--frames=N] [--table=all] [--seeds=N] [--lost=true]
[--OPTION=VALUE ...]``
prints the table of the hard scene, its options changed by any ``--OPTION=VALUE`` of the ``ir_rig`` scene
(``--strays=0``, ``--layout=bar``, ``--seed=4``, ...); ``--table=all`` prints the base scene, each condition
alone and all together; ``--seeds=N`` pools the frames of the scene's seeds 0 to N - 1 in each table;
``--lost=true`` first lists every frame lost (or ghost) with its cause and step.
"""

from __future__ import annotations

import sys
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from services.detection.blobs.node import Params as BlobsParams
from services.detection.blobs.node import detector
from services.estimation.bodies.labelled import Found, label_blobs, label_parts
from services.estimation.bodies.node import BodiesPerSet, Params, pixels, split_parts
from services.estimation.bodies.rigid import MatchOptions, pairwise_distances, within_gates
from services.geometry.absolute_orientation import least_squares_transforms
from services.geometry.camera_stack import CameraStack
from services.geometry.evaluation import pose_error
from services.geometry.se3 import transform_points
from services.synthetic import make_scene, scene_options
from services.synthetic.ir_rig import STRAY_RADIUS_FRACTION, IrRigScene

SPIN = 4.0
BASE: dict[str, Any] = {"camera_count": 3, "layouts": ("tool", "head"), "sphere_radius": 0.0075, "fps": 120.0}
CONDITIONS: dict[str, dict[str, Any]] = {"arc": {"layout": "arc"}, "strays": {"strays": 2}, "spin": {"spin": SPIN}}
HARD: dict[str, Any] = {**BASE, **{k: v for condition in CONDITIONS.values() for k, v in condition.items()}}
FRAMES = 360
GHOST_MM, GHOST_DEG = 5.0, 2.0
MERGE_MARGIN_PX, STRAY_PX, EDGE_PX, BLOB_PX, POINT_MM = 1.5, 10.0, 10.0, 1.0, 3.0
"""``MERGE_MARGIN_PX``: two discs whose rims are this close run into one blob (their anti-aliased edge pixels
above the threshold touch, 8-connected); seen from 1 px on, depending on where the pixel grid falls."""
CAUSES = ("merged", "hidden", "stray", "edge", "unknown")
STAGES = ("blobs", "labels", "pairing", "points", "residual", "search", "matching")


def hard_scene(**changes: Any) -> IrRigScene:
    """The hard scene (``HARD``) with ``changes`` to its options."""
    scene = make_scene("ir_rig", **{**HARD, **changes})
    assert isinstance(scene, IrRigScene)
    return scene


@dataclass(frozen=True)
class Discs:
    """Every bright disc of one frame in every camera: ``pixels`` (D, C, 2) the centres' images (through the
    distortion), ``radii`` (D, C) their image radii, px; ``lit`` (D, C) bool: in front of the camera, inside the
    image and not hidden; ``owner`` (D,) the body of each disc (``""`` for a stray), ``sphere`` (D,) its index
    in the body (-1 for a stray); ``world`` (D, 3) the centres, world frame."""

    pixels: np.ndarray
    radii: np.ndarray
    lit: np.ndarray
    owner: np.ndarray
    sphere: np.ndarray
    world: np.ndarray

    @classmethod
    def of(cls, scene: IrRigScene, stack: CameraStack, index: int) -> Discs:
        poses = scene.body_poses(index)
        strays = scene.strays_at(index)
        world = np.concatenate([*(transform_points(T, scene.bodies[name]) for name, T in poses.items()), strays])
        owner = np.array([name for name in poses for _ in scene.bodies[name]] + [""] * len(strays))
        sphere = np.array([j for name in poses for j in range(len(scene.bodies[name]))] + [-1] * len(strays))
        radius = np.where(owner == "", STRAY_RADIUS_FRACTION, 1.0) * scene.sphere_radius
        depths = stack.depths(world)
        with np.errstate(divide="ignore", invalid="ignore"):
            radii = stack.K[None, :, 0, 0] * radius[:, None] / depths
        image = stack.project(world)
        size = np.array([[c.width, c.height] for c in scene.cameras], np.float64)
        inside = np.all((image >= 0.0) & (image <= size[None] - 1.0), axis=2)
        hidden = np.zeros(inside.shape, bool)
        names = [c.name for c in scene.cameras]
        for camera, body, j in scene.occlusions(index):
            hidden[(owner == body) & (sphere == j), names.index(camera)] = True
        return cls(image, radii, inside & (depths > 2 * radius[:, None]) & ~hidden, owner, sphere, world)


@dataclass(frozen=True)
class Verdict:
    """One body in one frame: whether it is ``trackable``, ``outcome`` (``untrackable``, ``tracked``, ``ghost``,
    ``lost``), whether a ``predicted`` pose bridged it, the tracking pose's errors (NaN without one), and for a
    lost frame its ``cause`` (``CAUSES``) and ``stage`` (``STAGES``)."""

    index: int
    body: str
    trackable: bool
    outcome: str
    bridged: bool = False
    position_mm: float = float("nan")
    rotation_deg: float = float("nan")
    cause: str = ""
    stage: str = ""


def cause(scene: IrRigScene, discs: Discs, body: str, index: int) -> str:
    """The first of ``CAUSES`` that applies to ``body`` lost in frame ``index`` (module docstring)."""
    mine = discs.owner == body
    spheres = discs.owner != ""
    gap = np.linalg.norm(discs.pixels[:, None] - discs.pixels[None], axis=3)
    touching = gap < discs.radii[:, None] + discs.radii[None] + MERGE_MARGIN_PX
    both = discs.lit[:, None] & discs.lit[None] & touching
    both[np.arange(len(gap)), np.arange(len(gap))] = False
    if np.any(both[mine][:, spheres]):
        return "merged"
    if any(name == body for _, name, _ in scene.occlusions(index)):
        return "hidden"
    strays = ~spheres
    if np.any(strays):
        near_image = (gap[mine][:, strays] < STRAY_PX) & discs.lit[mine][:, None] & discs.lit[strays][None]
        centre = discs.world[mine].mean(axis=0)
        size = pairwise_distances(scene.bodies[body]).max()
        if np.any(near_image) or np.any(np.linalg.norm(discs.world[strays] - centre, axis=1) < size):
            return "stray"
    size = np.array([[c.width, c.height] for c in scene.cameras], np.float64)
    pixel = discs.pixels[mine]
    with np.errstate(invalid="ignore"):
        near_edge = np.any((pixel < EDGE_PX) & (pixel > -EDGE_PX), axis=2) | np.any(
            np.abs(pixel - (size[None] - 1.0)) < EDGE_PX, axis=2)
    return "edge" if np.any(near_edge) else "unknown"


def stage(scene: IrRigScene, discs: Discs, body: str, clean: list[np.ndarray], labels: np.ndarray | None,
          found: Found, match: MatchOptions) -> str:
    """The first of ``STAGES`` where ``body``, trackable and lost, fails (module docstring). ``clean[c]``: (N_c, 2)
    unflagged blobs of camera c then the parts of its split blobs, those the node triangulates; ``labels``: (N, C)
    the blob each of its spheres labels per camera (-1: none), None when it was not predicted; ``found``: the set's
    points and bodies."""
    mine = discs.owner == body
    truth = discs.world[mine]
    own_blob = np.full(discs.lit[mine].shape, -1, np.int64)
    for c, blobs in enumerate(clean):
        if len(blobs):
            distance = np.linalg.norm(discs.pixels[mine][:, c, None] - blobs[None], axis=2)
            near = (distance.min(axis=1) < BLOB_PX) & discs.lit[mine][:, c]
            own_blob[near, c] = distance.argmin(axis=1)[near]
    if np.count_nonzero(np.count_nonzero(own_blob >= 0, axis=1) >= 2) < 3:
        return "blobs"
    points = found.points_world
    to_truth = (np.linalg.norm(truth[:, None] - points[None], axis=2) if len(points)
                else np.full((len(truth), 1), np.inf))
    made = to_truth.min(axis=1) < POINT_MM / 1000.0
    if np.count_nonzero(made) < 3:
        if labels is not None and np.count_nonzero(np.count_nonzero(labels >= 0, axis=1) >= 2) < 3:
            return "labels"
        to_any = (np.linalg.norm(points[:, None] - discs.world[None], axis=2).min(axis=1) if len(points)
                  else np.zeros(0))
        for point, far in zip(found.points, to_any >= POINT_MM / 1000.0, strict=True):
            if far and any(own_blob[j, c] == i for c, i in zip(point.camera_indices, point.blob_indices, strict=True)
                           for j in range(len(truth))):
                return "pairing"
        return "points"
    nearest = points[to_truth.argmin(axis=1)]
    _, rms = least_squares_transforms(scene.bodies[body][None], nearest[None], made[None])
    if not within_gates(scene.bodies[body][None], made[None], rms, match)[0]:
        return "residual"
    return "search" if labels is None and np.count_nonzero(made) < len(truth) - 1 else "matching"


def analyse(scene: IrRigScene, frames: int = FRAMES) -> list[Verdict]:
    """Every body's ``Verdict`` in frames ``0 .. frames - 1`` of ``scene`` (module docstring)."""
    cameras = list(scene.cameras)
    params = Params(cameras=tuple(c.name for c in cameras))
    per_set = BodiesPerSet(scene.bodies, params)
    assert per_set.tracker is not None
    find = detector(BlobsParams())
    stack = CameraStack.of(cameras)
    verdicts = []
    for index in range(frames):
        images = scene.render(index).images
        found_blobs = [find(images[c.name]) for c in cameras]
        blobs = [pixels(b, params.flagged) for b in found_blobs]
        parts = [split_parts(b) for b in found_blobs]
        stamp_ns = round(scene.time_s(index) * 1e9)
        forecasts = {name: p.T_world_body for name, model in per_set.tracker.models.items()
                     if (p := model.predict(stamp_ns)) is not None}
        found, bridged = per_set(stamp_ns, cameras, blobs, parts)
        discs = Discs.of(scene, stack, index)
        labels = label_predicted(scene, stack, blobs, parts, forecasts, params.tracking.gate_px)
        usable = [np.concatenate([b, p.reshape(-1, 2)]) for b, p in zip(blobs, parts, strict=True)]
        truth = scene.body_poses(index)
        for name in scene.bodies:
            mine = discs.owner == name
            trackable = bool(np.count_nonzero(np.count_nonzero(discs.lit[mine], axis=1) >= 2) >= 3)
            match = found.matching.bodies.get(name)
            if match is not None:
                rotation, position = pose_error(match.fit.T_world_body, truth[name])
                position_mm, rotation_deg = 1000.0 * position, float(np.degrees(rotation))
                good = trackable and position_mm <= GHOST_MM and rotation_deg <= GHOST_DEG
                verdicts.append(Verdict(index, name, trackable, "tracked" if good else "ghost", False, position_mm,
                                        rotation_deg))
            elif not trackable:
                verdicts.append(Verdict(index, name, False, "untrackable", name in bridged))
            else:
                verdicts.append(Verdict(index, name, True, "lost", name in bridged,
                                        cause=cause(scene, discs, name, index),
                                        stage=stage(scene, discs, name, usable, labels.get(name), found,
                                                    params.match)))
    return verdicts


def label_predicted(scene: IrRigScene, stack: CameraStack, blobs: list[np.ndarray], parts: list[np.ndarray],
                    forecasts: dict[str, np.ndarray], gate_px: float) -> dict[str, np.ndarray]:
    """Name -> (N, C) the blob or split blob's part each sphere of each predicted body labels per camera (-1:
    none), as ``labelled.track_blobs`` labels them (all predicted bodies at once)."""
    if not forecasts:
        return {}
    names = list(forecasts)
    expected = np.concatenate([transform_points(forecasts[name], scene.bodies[name]) for name in names])
    on_blobs, projected = label_blobs(stack, blobs, expected, gate_px)
    labels, _ = label_parts(projected, blobs, parts, on_blobs, gate_px)
    first = np.cumsum([0] + [len(scene.bodies[name]) for name in names])
    return {name: labels[first[k]:first[k + 1]] for k, name in enumerate(names)}


def figures(verdicts: list[Verdict]) -> dict[str, dict[str, Any]]:
    """Per body: frames, trackable frames, tracked (and the share of the trackable), median errors of the tracked,
    ghosts, lost frames (those bridged by a predicted pose among them) and lost frames per cause and per stage."""
    out: dict[str, dict[str, Any]] = {}
    for name in dict.fromkeys(v.body for v in verdicts):
        mine = [v for v in verdicts if v.body == name]
        tracked = [v for v in mine if v.outcome == "tracked"]
        lost = [v for v in mine if v.outcome == "lost"]
        trackable = sum(v.trackable for v in mine)
        out[name] = {
            "frames": len(mine), "trackable": trackable, "tracked": len(tracked),
            "tracked_percent": 100.0 * len(tracked) / trackable if trackable else float("nan"),
            "position_mm_median": float(np.median([v.position_mm for v in tracked])) if tracked else float("nan"),
            "rotation_deg_median": float(np.median([v.rotation_deg for v in tracked])) if tracked else float("nan"),
            "ghosts": sum(v.outcome == "ghost" for v in mine), "lost": len(lost),
            "bridged": sum(v.bridged for v in lost),
            "causes": dict(Counter(v.cause for v in lost)), "stages": dict(Counter(v.stage for v in lost))}
    return out


def table(columns: list[tuple[str, dict[str, Any]]]) -> str:
    """A Markdown table of ``(heading, figures of one body)`` columns: a row per cause and per stage (lost frames),
    then the bridged, tracked, median errors and ghosts."""
    lines = ["| | " + " | ".join(heading for heading, _ in columns) + " |", "| --- |" + " --- |" * len(columns)]
    rows: list[tuple[str, Callable[[dict[str, Any]], str]]] = [
        *((f"lost: `{key}`", lambda f, key=key: str(f["causes"].get(key, 0))) for key in CAUSES),
        *((f"lost at: `{key}`", lambda f, key=key: str(f["stages"].get(key, 0))) for key in STAGES),
        ("lost (of which bridged)", lambda f: f"{f['lost']} ({f['bridged']})"),
        ("tracked / trackable", lambda f: f"{f['tracked']} / {f['trackable']}"),
        ("tracked", lambda f: f"{f['tracked_percent']:.1f} %"),
        ("position median", lambda f: f"{f['position_mm_median']:.3f} mm"),
        ("rotation median", lambda f: f"{f['rotation_deg_median']:.3f} deg"),
        ("ghosts", lambda f: str(f["ghosts"]))]
    for label, cell in rows:
        lines.append(f"| {label} | " + " | ".join(cell(body) for _, body in columns) + " |")
    return "\n".join(lines)


def conditions(which: str, changes: dict[str, Any]) -> list[tuple[str, dict[str, Any]]]:
    """``(title, changes to HARD)``: the hard scene with ``changes``, or with ``which == "all"`` the base scene, each
    condition alone and all together (each with ``changes``)."""
    if which != "all":
        described = ", ".join(f"{k}={v}" for k, v in changes.items())
        return [(f"hard scene{' with ' + described if described else ''}", changes)]
    off = {key: getattr(IrRigScene.Options(), key) for condition in CONDITIONS.values() for key in condition}
    found = [("base", {**off, **changes})]
    for name, condition in CONDITIONS.items():
        found.append((f"{name} alone", {**off, **condition, **changes}))
    found.append(("all (hard)", changes))
    return found


def main(arguments: list[str]) -> None:
    """The tables the command line asks for (module docstring); ``--seeds=N`` pools the scene's seeds 0 to N - 1."""
    options: dict[str, str] = {}
    for argument in arguments:
        name, sep, value = argument.removeprefix("--").partition("=")
        if not argument.startswith("--") or not sep:
            raise SystemExit(f"write options as --name=value, got {argument!r}")
        options[name] = value
    frames = int(options.pop("frames", FRAMES))
    which = options.pop("table", "hard")
    seeds = int(options.pop("seeds", 0))
    listed = options.pop("lost", "false") == "true"
    changes = scene_options("ir_rig", options)
    columns = []
    for title, changed in conditions(which, changes):
        verdicts = []
        for seed in range(seeds) if seeds else [changed.get("seed", 0)]:
            found = analyse(hard_scene(**{**changed, "seed": seed}), frames)
            verdicts += found
            for v in found if listed else []:
                if v.outcome in ("lost", "ghost"):
                    print(f"{title}, seed {seed}, frame {v.index}: {v.body} {v.outcome}"
                          f"{' (bridged)' if v.bridged else ''} {v.cause} {v.stage}")
        columns += [(f"{title}: {name}", body) for name, body in figures(verdicts).items()]
    pooled = f"seeds 0 to {seeds - 1} pooled, " if seeds else ""
    print(f"{pooled}{frames} frames each; a lost frame's cause and the step where it was lost:\n")
    print(table(columns))


if __name__ == "__main__":
    main(sys.argv[1:])
