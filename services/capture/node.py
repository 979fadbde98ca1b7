"""Capture node: publishes Image + CameraInfo (+ GroundTruth) frames from sources named by URI.

Every camera has its own keys (``<camera>/image``, ``/camera_info``, ``/truth``); the
frames of one instant share one header (stamp, sequence), whichever camera they come
from. Several URIs make a rig: their frames are taken in step, one from each.

Timing: with ``fps`` the node paces frames at that rate; without, it follows the source's
own timing (a video's timestamps, a TUM list, a scene's clock), devices pace themselves,
and image folders without times go at 30 fps; ``fps`` 0 sends frames as fast as they can be
taken. In a lossless run (``services.runtime.flow``) the pace is a ceiling: each frame waits
for the credits of the nodes that take the frames, then for at least a frame period after the
one before, and is never late. A finite source ends with an end of stream carrying the last
frame's ``seq``; one that sent no frame at all fails (``NodeError``). A source slower than its pace (a scene that
cannot render 1000 frames a second) sends each frame as soon as it has it: frames that go out
more than a frame period after their time (at least ``LATE_MIN_S``; ``LATE_S`` when paced by
the source's own timing) are counted as ``late`` (in the node's ``skipped`` statistics and on
its errors key, at the first one and then at most every ``LATE_REPORT_S``), and when the
source ends, one line says the rate it delivered against the one asked. Stamps are the
wall-clock time of capture (``stamps = "wall"``) or the source's own time (``"source"``, for
evaluating against a data set's ground truth). ``"wall"`` stamps of a source that is not a camera (a file,
a folder, a scene, a bag) follow the source's own clock from the wall-clock time of the first frame
(``services.runtime.stamps``): a frame that goes out late (held back by a slow node in a lossless run, or
by a busy machine) keeps the stamp of the instant its content stands for. CameraInfo comes from ``calib`` files (ROS
camera_info YAML, one per camera), else from the source (synthetic scenes know theirs, a KITTI
folder reads its ``calib.txt``, a ROS 2 bag has its ``camera_info`` topics); a camera with neither
publishes no CameraInfo, and trackers report it uncalibrated. Each calibrated camera's CameraInfo is
also answered on its ``<camera>/calibration`` queryable.

The calibrated cameras' ``T_rig_camera`` (parent frame ``rig``, child the camera's name) go
out once as ``StaticTransforms`` on ``tf_static/<node name>`` before the first frame, and are
answered on a queryable at the same key for whoever joins later.
"""

from __future__ import annotations

import functools
import logging
import time
from collections.abc import Callable
from pathlib import Path
from typing import Annotated, Any, ClassVar, Literal

import numpy as np
from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, field_validator, model_validator

from protocol.keys import KeyName
from protocol.message import Header
from protocol.poses import GroundTruth
from protocol.sensors import CameraInfo, Image
from protocol.spatial import RIG_FRAME, FrameTransform, StaticTransforms
from services.bus.pubsub import Role
from services.calibration.camera_info import CalibrationError, fit_to_image, read_camera_info
from services.capture.sources import (
    FrameFault,
    Source,
    SourceError,
    SourceFrame,
    VideoSource,
    camera_names,
    check_source,
    check_uri,
    frame_count,
    frame_sizes,
    open_source,
    rig_camera_names,
)
from services.convert import camera_info, frame_transforms, rig_static_transforms
from services.geometry.camera import CameraModel
from services.runtime.kind import NodeKind, SourceRole
from services.runtime.node import REPORT_EVERY_S, Node, NodeError
from services.runtime.stamps import SourceClock
from services.synthetic import scene_options

SETTLE_S = 0.3
"""Pause after the first subscriber appears, so its own outputs reach their subscribers too."""
UNTIMED_FPS = 30.0
LATE_S = 0.05
"""Without an asked ``fps``, a frame going out later than this after its time counts as late."""
LATE_MIN_S = 0.005
LATE_REPORT_S = 10.0
"""Late frames are reported at the first, then in batches at most this often, and at the end."""

_ENCODINGS = {(np.dtype(np.uint8), 1): "mono8", (np.dtype(np.uint16), 1): "mono16",
              (np.dtype(np.uint8), 3): "bgr8", (np.dtype(np.uint8), 4): "bgra8"}


def _as_tuple(value: Any) -> Any:
    return (value,) if isinstance(value, str | Path) else value


class Params(BaseModel):
    """Settings of a capture node; ``fps`` may change while it runs (``artrack config``, SIGHUP)."""

    model_config = ConfigDict(extra="forbid")
    RELOADABLE: ClassVar[frozenset[str]] = frozenset({"fps"})

    source: Annotated[tuple[str, ...], BeforeValidator(_as_tuple)] = Field(
        default=("synthetic:pattern",), min_length=1,
        description="camera:N, video:PATH, images:DIR, synthetic:SCENE or rosbag2:DIR; several make a rig")
    cameras: Annotated[tuple[KeyName, ...], BeforeValidator(_as_tuple)] = Field(
        default=(), description="camera names; default: the scene's own, else cam0, cam1, ...")
    fps: float | None = Field(default=None, ge=0, le=1000, description="pace (a ceiling in a lossless run); "
                              "0: as fast as frames are taken; default: the source's own timing")
    frames: int = Field(default=0, ge=0, description="stop after this many frames; 0 = until the source ends")
    prerender: int = Field(default=0, ge=0, le=10_000, description="a synthetic scene's first N instants rendered "
                           "before the first frame goes out, then sent over and over: no rendering while it runs "
                           "(for measuring what comes after it at high rates); 0: each frame rendered when due")
    loop: bool = Field(default=False, description="start finite sources over when they end")
    calib: Annotated[tuple[Path, ...], BeforeValidator(_as_tuple)] = Field(
        default=(), description="ROS camera_info YAML per camera")
    scene: dict[str, Any] = Field(default_factory=dict, description="options of a synthetic scene")
    stamps: Literal["wall", "source"] = Field(
        default="wall", description="wall: the wall-clock time of capture (a source other than a camera: its "
                                    "own clock from the first frame's); source: the source's own times")
    wait_for_subscriber: bool = Field(
        default=False, description="hold the first frame until every camera's images have a subscriber")

    @field_validator("source")
    @classmethod
    def _uris(cls, uris: tuple[str, ...]) -> tuple[str, ...]:
        for uri in uris:
            check_uri(uri)
        return uris

    @model_validator(mode="after")
    def _typed_scene_options(self) -> Params:
        """Scene options converted by each synthetic source's option types (text from a command line too)."""
        typed = dict(self.scene)
        for uri in self.source:
            scheme, name = check_uri(uri)
            if scheme == "synthetic":
                typed.update(scene_options(name, self.scene))
        if typed != self.scene:  # only when something changed: an untouched field stays unset
            self.scene = typed
        return self


class Rig:
    """The opened sources of a capture node, their camera names and calibration."""

    def __init__(self, params: Params):
        self.sources: list[Source] = []
        try:
            for uri in params.source:
                self.sources.append(open_source(uri, frames=params.frames, scene_options=params.scene,
                                                prerender=params.prerender))
        except SourceError:
            self.close()
            raise
        own = rig_camera_names([source.camera_names for source in self.sources])
        if params.cameras and len(params.cameras) != len(own):
            raise SourceError(f"{len(params.cameras)} camera names given for {len(own)} cameras")
        self.names = list(params.cameras or own)
        self.renames = [dict(zip(source.camera_names, names, strict=True))
                        for source, names in zip(self.sources, self._split(self.names), strict=True)]
        known = {rename[name]: model for source, rename in zip(self.sources, self.renames, strict=True)
                 for name, model in source.calibration.items()}
        if params.calib and len(params.calib) != len(self.names):
            raise SourceError(f"{len(params.calib)} calibration files given for {len(self.names)} cameras")
        self.origins = {name: source.uri for source, rename in zip(self.sources, self.renames, strict=True)
                        for name in rename.values()}
        for name, path in zip(self.names, params.calib, strict=False):
            known[name] = read_camera_info(path)
            self.origins[name] = str(path)
        self.calibration = known
        self._fitted: set[str] = set()

    def fit(self, name: str, image: np.ndarray, log: logging.Logger) -> None:
        """Hold camera ``name``'s calibration against the size of its first frame (``image``, (H, W[, C])):
        scaled to it once, said in one warning, when only the size differs; CalibrationError naming the
        file and both sizes when the aspect ratio does too."""
        if name in self._fitted or name not in self.calibration:
            return
        self._fitted.add(name)
        self.calibration[name], note = fit_to_image(self.calibration[name], image.shape[1], image.shape[0],
                                                    self.origins[name])
        if note is not None:
            log.warning("%s", note)

    def _split(self, names: list[str]) -> list[list[str]]:
        out, at = [], 0
        for source in self.sources:
            out.append(names[at: at + len(source.camera_names)])
            at += len(source.camera_names)
        return out

    def instants(self):
        """Frames of every source taken in step: lists of SourceFrame | FrameFault, one per source."""
        return zip(*(source.frames() for source in self.sources), strict=False)

    def close(self) -> None:
        for source in self.sources:
            source.close()


def run(node: Node, params: Params) -> None:
    try:
        rig = Rig(params)
    except (SourceError, ValueError) as exc:
        raise NodeError(str(exc)) from exc
    try:
        _publish(node, params, rig)
    finally:
        rig.close()


def _publish(node: Node, params: Params, rig: Rig) -> None:
    keys = node.keys
    live = node.configurable(params)
    images = {name: node.publisher(keys.image(name), Image, Role.FRAME) for name in rig.names}
    infos = {name: node.publisher(keys.camera_info(name), CameraInfo) for name in rig.calibration}
    for name in rig.calibration:
        node.answer(keys.calibration(name), functools.partial(_calibration, name, rig))
    truths = {name: node.publisher(keys.truth(name), GroundTruth)
              for source, rename in zip(rig.sources, rig.renames, strict=True)
              if source.uri.startswith("synthetic:") for name in rename.values()}
    if params.wait_for_subscriber:
        while node.running and not all(p.matched() for p in images.values()):
            node.wait(0.02)
        node.wait(SETTLE_S)
    if rig.calibration:
        _publish_static_transforms(node, rig)
    node.settle()
    seq = 0
    stamped = _StampedInfos(rig)
    late = _Lateness(node, keys.image(rig.names[0]))
    credits = node.credits()
    stamper = _Stamper(params, lambda: live.value.fps, scheduled=not _live(rig))
    while node.running and (params.frames == 0 or seq < params.frames):
        clock = _Pacer(lambda: live.value.fps, ceiling=credits is not None)
        for instant in rig.instants():
            if not node.running or (params.frames and seq >= params.frames):
                break
            faults = [f for f in instant if isinstance(f, FrameFault)]
            for source, fault in zip(rig.sources, instant, strict=True):
                if isinstance(fault, FrameFault):
                    node.report("frame_fault", f"frame {fault.index}: {fault.reason}", source.uri)
            if faults:
                continue
            if credits is not None and not credits.wait_for(seq, lambda: node.running):
                break
            late.count(clock.wait_for(node, instant[0].time_s, untimed=not _live(rig)), live.value.fps)
            started = time.perf_counter()
            try:
                for frame, rename in zip(instant, rig.renames, strict=True):
                    for own_name, image in frame.images.items():
                        rig.fit(rename[own_name], image, node.log)
            except CalibrationError as exc:
                raise NodeError(str(exc)) from exc
            header_stamp = _publish_instant(stamper, instant, rig, seq, stamped, images, infos, truths)
            node.processed(time.perf_counter() - started, header_stamp)
            if credits is not None:
                credits.sent(seq)
            seq += 1
        if not params.loop:
            break
    late.end(seq, live.value.fps, None if credits is None else credits.waited_s)
    if node.running and not params.loop:
        if seq == 0:
            raise NodeError(f"{', '.join(params.source)}: no frame could be read, none was sent")
        node.end_of_stream(seq - 1, seq)


def _publish_static_transforms(node: Node, rig: Rig) -> None:
    """Put the cameras' ``T_rig_camera`` once and answer them from now on (late joiners ask)."""
    key = node.keys.static_transforms(node.name)
    message = rig_static_transforms(Header(stamp_ns=time.time_ns(), frame_id=RIG_FRAME), rig.calibration)
    node.answer(key, lambda: message)
    node.publisher(key, StaticTransforms).put(message)


def _calibration(camera: str, rig: Rig) -> CameraInfo:
    """The calibration queryable's answer: the camera's CameraInfo (as fitted to its frames), stamped now."""
    return camera_info(Header(stamp_ns=time.time_ns(), frame_id=camera), rig.calibration[camera])


def _live(rig: Rig) -> bool:
    return _cameras(tuple(source.uri for source in rig.sources))


def _cameras(uris: tuple[str, ...]) -> bool:
    """Whether any of the source ``uris`` is a camera device (stamped by the wall clock as it captures)."""
    return any(uri.startswith("camera:") for uri in uris)


class _Stamper:
    """Each instant's stamp: its source time with ``stamps = "source"`` (when it has one); else, for a source that
    is not a camera (``scheduled``), its place on the source's own clock at the pace asked (``SourceClock``):
    the time its content stands for, whenever it goes out; else (a camera) the wall-clock time it is taken."""

    def __init__(self, params: Params, fps: Callable[[], float | None], scheduled: bool):
        self.source = params.stamps == "source"
        self.fps = fps
        self.clock = SourceClock() if scheduled else None

    def __call__(self, frame: SourceFrame) -> int:
        if self.source and frame.time_ns is not None:
            return frame.time_ns
        if self.clock is None:
            return time.time_ns()
        fps = self.fps()
        return self.clock.stamp(frame.time_ns, 1.0 / fps if fps else None)


def _publish_instant(stamper: _Stamper, instant: list[SourceFrame], rig: Rig, seq: int, stamped: _StampedInfos,
                     images, infos, truths) -> int:
    """Put one instant's messages under one header and return its stamp. Everything is built before the stamp
    is taken or right after it, cheaply; CameraInfo and GroundTruth go before the images, so a node that takes
    a frame has its calibration, and the images go last: a node of this process handed one starts on it while
    this thread has nothing more to do for the instant."""
    truth = {rename[own]: frame_transforms(frame.truth.get(own, []))
             for frame, rename in zip(instant, rig.renames, strict=True) for own in frame.images
             if rename[own] in truths}
    stamp = stamper(instant[0])
    messages = [message for frame, rename in zip(instant, rig.renames, strict=True)
                for message in _frame_messages(frame, rename, stamp, seq, stamped, truth)]
    for name, _, info, ground_truth in messages:
        if info is not None:
            infos[name].put(info)
        if ground_truth is not None:
            truths[name].put(ground_truth)
    for name, image, _, _ in messages:
        images[name].put(image)
    return stamp


def _frame_messages(frame: SourceFrame, rename: dict[str, str], stamp: int, seq: int, infos: _StampedInfos,
                    truth: dict[str, tuple[FrameTransform, ...]]) -> list[tuple[str, Image, CameraInfo | None,
                                                                              GroundTruth | None]]:
    """Per camera of ``frame``: its name, Image, CameraInfo (None uncalibrated) and GroundTruth (None without
    ``truth`` for it) under one header."""
    messages = []
    for own_name, image in frame.images.items():
        name = rename[own_name]
        header = Header(stamp_ns=stamp, frame_id=name, seq=seq)
        encoding = _ENCODINGS[(image.dtype, image.shape[2] if image.ndim == 3 else 1)]
        messages.append((name, Image(header=header, encoding=encoding, data=image), infos.under(header),
                         None if name not in truth else GroundTruth(header=header, transforms=truth[name])))
    return messages


class _StampedInfos:
    """Each calibrated camera's CameraInfo, built once per calibration and put under each frame's header."""

    def __init__(self, rig: Rig):
        self.rig = rig
        self._built: dict[str, tuple[CameraModel, CameraInfo]] = {}

    def under(self, header: Header) -> CameraInfo | None:
        """The CameraInfo of camera ``header.frame_id`` with ``header``, None when it has no calibration."""
        camera = self.rig.calibration.get(header.frame_id)
        if camera is None:
            return None
        built = self._built.get(header.frame_id)
        if built is None or built[0] is not camera:
            built = camera, camera_info(header, camera)
            self._built[header.frame_id] = built
        return built[1].model_copy(update={"header": header})


class _Pacer:
    """Sleeps so frames leave at ``fps()``, or at the source's own pace (its frame times); ``fps()`` 0:
    no pacing at all. The sleeps are ``Node.wait_until``'s, with the thread's timer slack at 1 ns.

    ``fps()`` is asked before every frame: when it changes, pacing starts over from that frame.
    With ``ceiling`` (a lossless run) the pace starts over whenever a frame went out late: frames
    never go out faster than the pace to catch up, and none is late.
    """

    def __init__(self, fps: Callable[[], float | None], ceiling: bool = False):
        self.fps = fps
        self.ceiling = ceiling
        self.period: float | None = None
        self.start_wall: float | None = None
        self.start_source: float | None = None
        self.count = 0

    def wait_for(self, node: Node, time_s: float | None, untimed: bool) -> float:
        """Sleep until the next frame is due; return how late it is already (seconds, 0 when on time)."""
        now = time.monotonic()
        fps = self.fps()
        if fps == 0:
            return 0.0
        period = None if fps is None else 1.0 / fps
        if self.start_wall is None or period != self.period:
            self.start_wall, self.start_source, self.count, self.period = now, time_s, 0, period
        if self.period is not None:
            due = self.start_wall + self.count * self.period
        elif time_s is not None and self.start_source is not None:
            due = self.start_wall + (time_s - self.start_source)
        elif untimed:
            due = self.start_wall + self.count / UNTIMED_FPS
        else:
            due = now
        self.count += 1
        if self.ceiling and due < now and self.count > 1:
            self.start_wall, self.start_source, self.count = now, time_s, 1
            return 0.0
        node.wait_until(due)
        return max(0.0, now - due)


class _Lateness:
    """Counts frames that went out late (``wait_for`` said so) and reports them on ``key``: the first at
    once, then at most every LATE_REPORT_S; ``end`` reports the rest and the rate delivered."""

    def __init__(self, node: Node, key: str):
        self.node = node
        self.key = key
        self.late = 0
        self.unreported = 0
        self.reported_at: float | None = None
        self.first: float | None = None
        self.last = 0.0

    def count(self, behind_s: float, fps: float | None) -> None:
        now = time.monotonic()
        self.first = now if self.first is None else self.first
        self.last = now
        if behind_s <= max(LATE_MIN_S, LATE_S if not fps else 1.0 / fps):
            return
        self.late += 1
        self.unreported += 1
        if self.reported_at is None or now - self.reported_at >= LATE_REPORT_S:
            asked = f"the {fps:g} fps asked" if fps else "its own timing"
            self._report(f"the source cannot keep up with {asked}: frames go out late ({behind_s:.2f} s behind)")

    def end(self, frames: int, fps: float | None, held_s: float | None = None) -> None:
        """Report what is left, with the rate the ``frames`` sent went out at against the one asked, and
        how long the nodes taking them held them back (``held_s``, a lossless run)."""
        if self.first is None:
            return
        span = self.last - self.first
        rate = (frames - 1) / span if frames > 1 and span > 0 else None
        delivered = f"{rate:.1f} fps" if rate is not None else "?"
        asked = f" of the {fps:g} asked" if fps else ""
        held = f", lossless: held back {held_s:.1f} s in all by the nodes taking them" if held_s is not None else ""
        if not self.late:
            self.node.log.info("%d frames sent at %s%s%s", frames, delivered, asked, held)
            return
        detail = f"{self.late} of {frames} frames late: the source delivered {delivered}{asked}"
        if not self._report(detail):  # too soon after the last report for the node to log this one
            self.node.log.warning("late on %s (%d so far): %s", self.key, self.late, detail)

    def _report(self, detail: str) -> bool:
        """Report the late frames not reported yet; whether the node logs it (at most once a second)."""
        logged = self.reported_at is None or time.monotonic() - self.reported_at >= REPORT_EVERY_S
        self.node.report("late", detail, self.key, self.unreported)
        self.unreported = 0
        self.reported_at = time.monotonic()
        return logged


def _outputs(params: Params) -> tuple[str, ...]:
    names = params.cameras or camera_names(params.source, params.scene)
    return tuple(f"{name}/{stream}" for name in names for stream in ("image", "camera_info", "truth"))


def _check(params: Params) -> None:
    """The sources can be opened (camera devices too), the calibration files read, and each file fits its
    camera's frames where their size is known before capturing (scenes, image folders, video files)."""
    try:
        for uri in params.source:
            scheme, rest = check_source(uri)
            if scheme == "camera":  # a device that does not open is refused before the job says it runs
                VideoSource(uri, int(rest), live=True).close()
        sizes = frame_sizes(params.source, params.scene) if params.calib else []
    except SourceError as exc:
        raise ValueError(str(exc)) from exc
    for path, size in zip(params.calib, sizes, strict=False):
        camera = read_camera_info(path)
        if size is not None:
            fit_to_image(camera, *size, str(path))


def _frame_sizes(params: Params) -> dict[str, tuple[int, int]]:
    """``{camera: (width, height)}`` of the cameras whose frame size is known before capturing (``frame_sizes``)."""
    try:
        names = params.cameras or camera_names(params.source, params.scene)
        sizes = frame_sizes(params.source, params.scene)
    except SourceError as exc:
        raise ValueError(str(exc)) from exc
    return {name: size for name, size in zip(names, sizes, strict=False) if size is not None}


def _finite(params: Params) -> bool:
    """Whether the capture ends by itself: no loop, no camera device, and a frame count for a scene."""
    schemes = [check_uri(uri)[0] for uri in params.source]
    return not params.loop and "camera" not in schemes and (bool(params.frames) or "synthetic" not in schemes)


def _frames(params: Params) -> int | None:
    """Frames per camera the capture will send: the fewest its sources hold, bounded by ``frames``."""
    if not _finite(params):
        return None
    counts = [frame_count(uri) for uri in params.source if check_uri(uri)[0] != "synthetic"]
    known = [n for n in counts if n is not None]
    if len(known) < len(counts):
        return params.frames or None
    return min([*known, params.frames] if params.frames else known)


KIND = NodeKind(name="capture", summary="publishes camera frames + calibration from a source",
                params=Params, run=run, inputs=(), outputs=_outputs, check=_check,
                source=SourceRole(finite=_finite, frames=_frames, fps=lambda params: params.fps,
                                  wall_stamps=lambda params: params.stamps == "wall" and _cameras(params.source),
                                  sizes=_frame_sizes))
