"""Frame sources named by URI: cameras, video files, image folders, synthetic scenes.

==========================  ==============================================================
``camera:N``                video device N through cv2.VideoCapture
``video:PATH``              any file OpenCV reads; frame times from the container
``images:DIR``              sorted image files; a TUM ``rgb.txt`` or KITTI ``times.txt`` in DIR
                            (or its parent, for KITTI) gives the frame times, and so do file
                            names that are numbers (TUM's ``<timestamp>.png``). A DIR with no
                            images but sub-folders of them (``cam0/``, ``cam1/``, ...) is a rig:
                            one camera per sub-folder, named after it, frames paired by time
                            (or by file name when the folders have no times). A KITTI folder
                            ``image_<i>`` is calibrated by the ``P<i>`` line of the ``calib.txt``
                            beside it (``services.calibration.kitti``)
``synthetic:SCENE``         a rendered scene with exact ground truth (services.synthetic)
``rosbag2:DIR``             a ROS 2 bag's image topics, calibrated by their ``camera_info`` topics;
                            ``rosbag2:DIR?topic=/cam0/image_raw`` takes that one (services.capture.rosbag)
==========================  ==============================================================

A source that cannot start (no device, missing or unreadable file, empty folder) raises
:class:`SourceError` naming it; FFmpeg's own messages are silenced (``OPENCV_FFMPEG_LOGLEVEL``,
read once per process, unless already set: 16 shows its errors), so that is the one line said.
A frame that cannot be read mid-stream comes out as a :class:`FrameFault` so the caller can log,
count and skip it. Pure: no bus here.
"""

from __future__ import annotations

import os
import re
from abc import ABC, abstractmethod
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from services.calibration.image_folder import (
    IMAGE_SUFFIXES,
    ImageFolderError,
    folder_entries,
    is_image,
    read_image,
)
from services.calibration.kitti import folder_camera
from services.capture.rosbag import Bag, BagError, Frame, split_uri
from services.geometry.camera import CameraModel
from services.synthetic import make_scene
from services.synthetic.base import Truth

MAX_CONSECUTIVE_FAULTS = 30

os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")  # AV_LOG_QUIET, before the first cv2.VideoCapture


class SourceError(RuntimeError):
    """A source that cannot deliver frames at all; the message names it and says why."""


@dataclass(frozen=True)
class SourceFrame:
    """One instant of a source: ``images`` and ``truth`` by camera name.

    ``time_ns``: the source's own time of the frame, int nanoseconds (epoch time for TUM lists
    and TUM file names, time from the start for videos, KITTI times and scenes), None when it
    has none. Times written as decimal seconds in a folder are taken exactly
    (``services.calibration.image_folder``).
    Images are (H, W) or (H, W, 3|4) uint8/uint16 as OpenCV reads them.
    """

    index: int
    time_ns: int | None
    images: dict[str, np.ndarray]
    truth: dict[str, Truth] = field(default_factory=dict)

    @property
    def time_s(self) -> float | None:
        """``time_ns`` in seconds (for pacing; stamps use ``time_ns``)."""
        return None if self.time_ns is None else self.time_ns / 1_000_000_000  # int / int: correctly rounded


@dataclass(frozen=True)
class FrameFault:
    """Frame ``index`` could not be read; ``reason`` says why."""

    index: int
    reason: str


class Source(ABC):
    """Base of every source: a URI, its cameras' names, their calibration when known."""

    uri: str
    camera_names: tuple[str, ...] = ("cam0",)

    @property
    def calibration(self) -> dict[str, CameraModel]:
        """Calibration the source itself knows, by camera name (synthetic scenes)."""
        return {}

    @abstractmethod
    def frames(self) -> Iterator[SourceFrame | FrameFault]:
        """Frames from the start of the source, in order."""

    def close(self) -> None:  # noqa: B027 - most sources hold nothing to release
        """Release devices and files (idempotent)."""


class ImageFolderSource(Source):
    """Image files of a folder, in order, with times when the folder says them."""

    def __init__(self, uri: str, folder: Path):
        self.uri = uri
        self.folder = folder
        if not folder.is_dir():
            raise SourceError(f"{uri}: no such folder")
        self.entries = _entries(uri, folder)
        if not self.entries:
            raise SourceError(f"{uri}: no image files in {folder} ({', '.join(sorted(IMAGE_SUFFIXES))})")

    def frames(self) -> Iterator[SourceFrame | FrameFault]:
        for index, (path, time_ns) in enumerate(self.entries):
            image = read_image(path)
            if image is None:
                yield FrameFault(index, f"cannot read {path}")
                continue
            yield SourceFrame(index, time_ns, {self.camera_names[0]: image})

    @property
    def calibration(self) -> dict[str, CameraModel]:
        """A KITTI folder's camera, from its ``calib.txt`` (CalibrationError for a damaged one); else none."""
        size = self.first_image_size()
        camera = folder_camera(self.folder, self.camera_names[0], *size) if size is not None else None
        return {} if camera is None else {camera.name: camera}

    def first_image_size(self) -> tuple[int, int] | None:
        """``(width, height)`` of the first image that reads, None when none does."""
        for path, _ in self.entries:
            image = read_image(path)
            if image is not None:
                return image.shape[1], image.shape[0]
        return None


def camera_folders(folder: Path) -> list[Path]:
    """The sub-folders of ``folder`` holding image files, in natural name order (cam2 before cam10),
    when ``folder`` itself holds no image files nor a TUM ``rgb.txt``; empty otherwise."""
    if not folder.is_dir() or (folder / "rgb.txt").is_file() or any(is_image(p) for p in folder.iterdir()):
        return []
    subfolders = [p for p in folder.iterdir() if p.is_dir() and any(is_image(f) for f in p.iterdir())]
    return sorted(subfolders, key=lambda p: [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", p.name)])


class CameraFoldersSource(Source):
    """A rig in one folder: a sub-folder of images per camera (named after it), one frame per instant.

    Frames are paired by their time when every folder has times (``folder_entries``), else by file
    name; SourceError (one line) when a folder has a frame the others lack, or when some folders have
    times and others not. An instant's ``time_ns`` is its shared time (None when paired by name).
    """

    def __init__(self, uri: str, folders: list[Path]):
        self.uri = uri
        self.folders = folders
        self.camera_names = tuple(folder.name for folder in folders)
        entries = {folder.name: _entries(uri, folder) for folder in folders}
        timed = {name: all(t is not None for _, t in rows) for name, rows in entries.items()}
        if len(set(timed.values())) > 1:
            with_times = ", ".join(name for name, has in timed.items() if has)
            raise SourceError(f"{uri}: the camera folders do not pair up: {with_times} have frame times, "
                              f"{', '.join(name for name, has in timed.items() if not has)} not")
        by_time = all(timed.values())
        keyed: dict[str, dict[int | str, Path]] = {}
        for name, rows in entries.items():
            keys: list[int | str] = [t if by_time and t is not None else path.stem for path, t in rows]
            if len(set(keys)) != len(keys):
                raise SourceError(f"{uri}: {name}/ has two frames with one {'time' if by_time else 'file name'}")
            keyed[name] = dict(zip(keys, (path for path, _ in rows), strict=True))
        first = self.camera_names[0]
        for name in self.camera_names[1:]:
            for a, b in ((first, name), (name, first)):
                missing = [key for key in keyed[a] if key not in keyed[b]]
                if missing:
                    raise SourceError(f"{uri}: the camera folders do not pair up: {a}/{keyed[a][missing[0]].name} "
                                      f"has no partner in {b}/ ({len(missing)} such frames; {len(keyed[a])} "
                                      f"in {a}/, {len(keyed[b])} in {b}/)")
        order = sorted(keyed[first]) if by_time else list(keyed[first])
        self.instants = [(key if isinstance(key, int) else None, {name: keyed[name][key] for name in self.camera_names})
                         for key in order]

    def frames(self) -> Iterator[SourceFrame | FrameFault]:
        for index, (time_ns, paths) in enumerate(self.instants):
            images = {name: read_image(path) for name, path in paths.items()}
            unread = [str(path) for name, path in paths.items() if images[name] is None]
            if unread:
                yield FrameFault(index, f"cannot read {', '.join(unread)}")
                continue
            yield SourceFrame(index, time_ns, {name: image for name, image in images.items() if image is not None})

    @property
    def calibration(self) -> dict[str, CameraModel]:
        """The cameras of KITTI folders (``image_<i>``, from the ``calib.txt`` beside them), in the frame of the
        file's camera 0; none for other folders."""
        cameras = [folder_camera(folder, folder.name, *size) for folder, size
                   in zip(self.folders, self.first_image_sizes(), strict=True) if size is not None]
        return {camera.name: camera for camera in cameras if camera is not None}

    def first_image_sizes(self) -> list[tuple[int, int] | None]:
        """``(width, height)`` of each camera's first image, None where it does not read."""
        sizes: list[tuple[int, int] | None] = []
        for name in self.camera_names:
            image = read_image(self.instants[0][1][name]) if self.instants else None
            sizes.append(None if image is None else (image.shape[1], image.shape[0]))
        return sizes


def _entries(uri: str, folder: Path) -> list[tuple[Path, int | None]]:
    """``folder_entries`` of ``folder``; SourceError naming the list and the line when a time there is not one."""
    try:
        return folder_entries(folder)
    except ImageFolderError as exc:
        raise SourceError(str(exc)) from None


@contextmanager
def opencv_silenced() -> Iterator[None]:
    """OpenCV's own log off (its backends' ``[ WARN:...] global cap_v4l.cpp`` lines when a device does not open,
    which the SourceError says in one line), then back to its level."""
    before = cv2.utils.logging.getLogLevel()
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)
    try:
        yield
    finally:
        cv2.utils.logging.setLogLevel(before)


class VideoSource(Source):
    """Frames of a video file or a camera device, through cv2.VideoCapture."""

    def __init__(self, uri: str, target: str | int, live: bool):
        self.uri = uri
        self.live = live
        with opencv_silenced():
            self.capture = cv2.VideoCapture(target)
        if not self.capture.isOpened():
            self.capture.release()
            raise SourceError(f"{uri}: {_not_opened(target) if live else 'OpenCV cannot read this file'}")
        self.count = -1 if live else int(self.capture.get(cv2.CAP_PROP_FRAME_COUNT))

    def frames(self) -> Iterator[SourceFrame | FrameFault]:
        index, faults = 0, 0
        while self.capture.isOpened():
            ok, image = self.capture.read()
            if not ok:
                if not self.live and index >= self.count:
                    return
                faults += 1
                if faults > MAX_CONSECUTIVE_FAULTS:
                    raise SourceError(f"{self.uri}: {faults} frames in a row could not be read, giving up")
                yield FrameFault(index, "frame could not be decoded")
                index += 1
                continue
            faults = 0
            time_ns = None if self.live else round(self.capture.get(cv2.CAP_PROP_POS_MSEC) * 1e6)
            yield SourceFrame(index, time_ns, {self.camera_names[0]: image})
            index += 1

    def close(self) -> None:
        self.capture.release()


def _not_opened(device: str | int) -> str:
    """Why camera ``device`` did not open, as far as the system tells: no device file, or one that does not open."""
    node = Path(f"/dev/video{device}")
    if isinstance(device, int) and Path("/dev").is_dir() and not node.exists():
        return f"cannot open video device {device} (there is no {node})"
    return f"cannot open video device {device}"


class SceneSource(Source):
    """A synthetic scene: rendered frames with exact ground truth and known calibration.

    With ``prerender`` N > 0, the scene's first N instants are rendered before the first frame goes out,
    then sent over and over (frame k is instant k mod N, with its ground truth, timed as frame k): a
    source that costs no rendering while it runs, as a camera costs its host little, for measuring
    what comes after it at high rates.
    """

    def __init__(self, uri: str, scene_name: str, frames: int, options: dict, prerender: int = 0):
        self.uri = uri
        try:
            self.scene = make_scene(scene_name, **options)
        except ValueError as exc:
            raise SourceError(f"{uri}: {exc}") from exc
        self.count = frames
        self.prerender = prerender
        self.camera_names = tuple(c.name for c in self.scene.cameras)

    @property
    def calibration(self) -> dict[str, CameraModel]:
        return {c.name: c for c in self.scene.cameras}

    def frames(self) -> Iterator[SourceFrame | FrameFault]:
        rendered = [self.scene.render(i) for i in range(self.prerender)]
        period_ns = rendered[1].time_s * 1e9 - rendered[0].time_s * 1e9 if len(rendered) > 1 else 0.0
        index = 0
        while self.count == 0 or index < self.count:
            if rendered:
                frame = rendered[index % len(rendered)]
                yield SourceFrame(index, round(index * period_ns), frame.images, frame.truth)
            else:
                frame = self.scene.render(index)
                yield SourceFrame(index, round(frame.time_s * 1e9), frame.images, frame.truth)
            index += 1


class RosbagSource(Source):
    """The image topics of a ROS 2 bag, in step, timed by their header stamps (``services.capture.rosbag``)."""

    def __init__(self, uri: str, rest: str):
        self.uri = uri
        self.bag = _bag(uri, rest)
        self.camera_names = tuple(self.bag.cameras.values())

    @property
    def calibration(self) -> dict[str, CameraModel]:
        try:
            return self.bag.calibration()
        except ValueError as exc:
            raise SourceError(f"{self.uri}: {exc}") from exc

    def frames(self) -> Iterator[SourceFrame | FrameFault]:
        for index, frame in enumerate(self.bag.frames()):
            if isinstance(frame, Frame):
                yield SourceFrame(index, frame.time_ns, frame.images)
            else:
                yield FrameFault(index, frame[1])


def _bag(uri: str, rest: str) -> Bag:
    """The bag of a ``rosbag2:`` URI; SourceError naming the URI and why when it cannot be one."""
    try:
        return Bag(*split_uri(rest))
    except BagError as exc:
        raise SourceError(f"{uri}: {exc}") from exc


SCHEMES = ("camera", "video", "images", "synthetic", "rosbag2")


def check_uri(uri: str) -> tuple[str, str]:
    """``(scheme, rest)`` of a well-formed source URI; ValueError saying what a URI looks like otherwise."""
    scheme, _, rest = uri.partition(":")
    if not rest or scheme not in SCHEMES:
        raise ValueError(f"{uri!r} is not a source URI (camera:N, video:PATH, images:DIR, synthetic:SCENE or "
                         "rosbag2:DIR)")
    if scheme == "camera" and not rest.isdigit():
        raise ValueError(f"{uri!r}: the camera is a device number, e.g. camera:0")
    return scheme, rest


def rig_camera_names(own: list[tuple[str, ...]]) -> list[str]:
    """Names of a rig's cameras from each source's own: a lone source keeps them, several give cam0, cam1, ..."""
    flat = [name for names in own for name in names]
    return flat if len(own) == 1 else [f"cam{i}" for i in range(len(flat))]


def camera_names(uris: tuple[str, ...], scene_options: dict) -> list[str]:
    """The names the capture node gives the cameras of ``uris``, without opening devices or files."""
    own: list[tuple[str, ...]] = []
    for uri in uris:
        scheme, rest = check_uri(uri)
        folders = camera_folders(Path(rest).expanduser()) if scheme == "images" else []
        if folders:
            own.append(tuple(folder.name for folder in folders))
            continue
        if scheme == "rosbag2":
            try:
                own.append(tuple(_bag(uri, rest).cameras.values()))
            except SourceError:  # one camera here: the pre-start check (``check_source``) says why it does not open
                own.append(("cam0",))
            continue
        if scheme != "synthetic":
            own.append(("cam0",))
            continue
        try:
            own.append(tuple(camera.name for camera in make_scene(rest, **scene_options).cameras))
        except ValueError as exc:
            raise SourceError(f"{uri}: {exc}") from exc
    return rig_camera_names(own)


def frame_sizes(uris: tuple[str, ...], scene_options: dict) -> list[tuple[int, int] | None]:
    """``(width, height)`` of each camera's frames, in rig order, where known before capturing: a
    scene's cameras, an image folder's first image, a video file's frames; None for devices (and
    for what cannot be read). Raises SourceError for a URI that cannot name a source."""
    sizes: list[tuple[int, int] | None] = []
    for uri in uris:
        scheme, rest = check_source(uri)
        path = Path(rest).expanduser()
        if scheme == "synthetic":
            try:
                sizes.extend((c.width, c.height) for c in make_scene(rest, **scene_options).cameras)
            except ValueError as exc:
                raise SourceError(f"{uri}: {exc}") from exc
        elif scheme == "images" and camera_folders(path):
            sizes.extend(CameraFoldersSource(uri, camera_folders(path)).first_image_sizes())
        elif scheme == "images":
            sizes.append(ImageFolderSource(uri, path).first_image_size())
        elif scheme == "rosbag2":
            sizes.extend(_bag(uri, rest).first_sizes())
        elif scheme == "video":
            capture = cv2.VideoCapture(str(path))
            width, height = int(capture.get(cv2.CAP_PROP_FRAME_WIDTH)), int(capture.get(cv2.CAP_PROP_FRAME_HEIGHT))
            capture.release()
            sizes.append((width, height) if width > 0 and height > 0 else None)
        else:
            sizes.append(None)
    return sizes


def frame_count(uri: str) -> int | None:
    """Frames a file or folder source holds, told without capturing; None for devices, scenes (their
    count is a parameter) and what cannot be read."""
    try:
        scheme, rest = check_source(uri)
    except SourceError:
        return None
    path = Path(rest).expanduser()
    if scheme == "rosbag2":
        return _bag(uri, rest).frame_count()
    if scheme == "images":
        listing = path / "rgb.txt"
        if listing.is_file():
            return sum(1 for line in listing.read_text().splitlines()
                       if len(line.split()) >= 2 and not line.lstrip().startswith("#"))
        return sum(1 for p in path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file())
    if scheme == "video":
        capture = cv2.VideoCapture(str(path))
        try:
            count = int(capture.get(cv2.CAP_PROP_FRAME_COUNT))
        finally:
            capture.release()
        return count if count > 0 else None
    return None


def check_source(uri: str) -> tuple[str, str]:
    """``(scheme, rest)`` of ``uri`` once what can be told without capturing is right: the URI's
    form, a video file that exists and OpenCV opens, an image folder that exists, camera folders
    that pair up (SourceError otherwise)."""
    try:
        scheme, rest = check_uri(uri)
    except ValueError as exc:
        raise SourceError(str(exc)) from exc
    path = Path(rest).expanduser()
    if scheme == "video" and path.is_dir():
        raise SourceError(f"{uri}: a folder, not a video file (a folder of images is images:{rest})")
    if scheme == "video" and not path.is_file():
        raise SourceError(f"{uri}: no such file")
    if scheme == "video":
        VideoSource(uri, str(path), live=False).close()
    if scheme == "images" and not path.is_dir():
        raise SourceError(f"{uri}: no such folder")
    if scheme == "images" and camera_folders(path):
        CameraFoldersSource(uri, camera_folders(path))  # folders that do not pair up are refused here
    if scheme == "rosbag2":
        _bag(uri, rest)  # a missing folder, a folder that is no bag, a bag with no image topic
    return scheme, rest


def open_source(uri: str, *, frames: int = 0, scene_options: dict | None = None, prerender: int = 0) -> Source:
    """Open the source named by ``uri``; ``frames`` bounds a synthetic scene (0 = endless), ``prerender`` renders
    its first instants before it starts and cycles them (``SceneSource``)."""
    scheme, rest = check_source(uri)
    if scheme == "camera":
        return VideoSource(uri, int(rest), live=True)
    if scheme == "video":
        return VideoSource(uri, str(Path(rest).expanduser()), live=False)
    if scheme == "images" and camera_folders(Path(rest).expanduser()):
        return CameraFoldersSource(uri, camera_folders(Path(rest).expanduser()))
    if scheme == "images":
        return ImageFolderSource(uri, Path(rest).expanduser())
    if scheme == "rosbag2":
        return RosbagSource(uri, rest)
    return SceneSource(uri, rest, frames, scene_options or {}, prerender)
