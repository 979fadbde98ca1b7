"""Local mapping in a process of its own: the tracker never shares an interpreter lock with it.

The tracker keeps its map (``MapDatabase``); the mapping process keeps a copy and is the only one to
change points and keyframe poses. They talk through a queue (to the mapper) and a pipe (back):

* to the mapper: ``reset`` (a whole map, ``map.sync.snapshot``: after the map is started or loaded, or
  bridged by the tracker, ``bridging``), ``keyframe`` (a new keyframe as the tracker made it, with the
  tracking counters added since the last message, ``map.sync.take_counts``; one the mapper already holds,
  sent with a reset, is only mapped) and ``stop``;
* to the tracker: ``ready`` once, then for each keyframe ``points`` after each of its neighbours gave
  new points and after their fusion (what changed so far, ``map.sync.take_changes``: the tracker needs
  new points first, as it gets them from a mapping thread), ``calibration`` once, before the ``mapped``
  of the keyframe after which the mapper checked the camera matrix (``LocalMapper.check_calibration``),
  and ``mapped`` once its mapping is done (what changed since, and the mapper's stage times, wall and CPU
  milliseconds); ``stopped`` at the end.

A thread of the tracker's process reads the messages off the pipe as they come; the tracker brings
the changes in before each frame and when it asks whether the mapper is idle (``sync``,
``map.sync.apply_changes``); keyframes it made that the
mapper has not processed yet keep their observations. ``idle`` (no keyframe waiting) feeds the
keyframe decision as the thread's does; ``wait_idle`` brings the changes in as they come until the
mapper has none left to send.

Start: a spawned process imports NumPy, OpenCV and pycolmap again (about 0.5 s, seconds on a loaded
machine), then waits for its camera (``camera``: intrinsics, image size, settings, pyramid) and says
``ready``. ``MappingProcess`` waits for that ``ready`` (``MappingProcessError`` if the process ends first or
is not ready within ``START_TIMEOUT_S``): its first keyframes must not wait for a process still importing
(a camera moving fast, KITTI at 10 Hz, loses a map whose first keyframes bring no new points in time). So
that no frame waits for the imports, ``prepare`` spawns a process ahead of time, which the next
``MappingProcess`` takes: the SLAM node does it when it starts, before its first frame.

Costs: the changes are unpickled in the tracker's thread, the frame's ``map_sync`` stage (measured by
``tests/bench/slam_tracking.py``, figures in docs/benchmarks.md).
"""

from __future__ import annotations

import atexit
import dataclasses
import logging
import multiprocessing
import pickle
import queue
import signal
import threading
import time
from typing import Any

import numpy as np

from services.slam.calibration_check import FocalCheck
from services.slam.map import sync
from services.slam.map.database import MapDatabase
from services.slam.mapping import LocalMapper, MappedKeyframe
from services.slam.settings import SlamSettings

__all__ = ["MappingProcess", "MappingProcessError"]

logger = logging.getLogger(__name__)

START_TIMEOUT_S = 60.0
STOP_TIMEOUT_S = 60.0
PARENT_CHECK_S = 0.5
"""The mapping process looks this often whether the process that started it still runs (it ends if not)."""


class MappingProcessError(RuntimeError):
    """The mapping process did not start."""


class _Spawned:
    """A mapping process spawned (not told its camera yet), its queue, and its pipe back read by a thread
    as messages come (a full pipe would hold the process up, and a message read only while it is being
    written would come a frame late), until the pipe ends with the process."""

    def __init__(self) -> None:
        context = multiprocessing.get_context("spawn")
        self.inbox: Any = context.Queue()
        self.outbox, writer = context.Pipe(duplex=False)
        self.process = context.Process(target=_serve, name="slam-mapping", daemon=True, args=(self.inbox, writer))
        _start_deaf_to_ctrl_c(self.process)
        writer.close()  # the process holds the only writing end: its end is the pipe's
        self.received: queue.Queue[bytes] = queue.Queue()
        threading.Thread(target=self._drain, name="slam-mapping-receiver", daemon=True).start()

    def _drain(self) -> None:
        while True:
            try:
                self.received.put(self.outbox.recv_bytes())
            except (EOFError, OSError):
                self.received.put(pickle.dumps(("ended", f"it ended (exit code {self.process.exitcode})")))
                return


_spare: _Spawned | None = None
_spare_lock = threading.Lock()


def prepare() -> None:
    """Spawn a mapping process now (unless one waits already) for the next ``MappingProcess`` to take, so
    that its imports are done before a map needs it."""
    global _spare
    with _spare_lock:
        if _spare is None or not _spare.process.is_alive():
            _spare = _Spawned()
            atexit.unregister(_end_spare)
            atexit.register(_end_spare)


def _end_spare() -> None:
    """At exit, kill the spare mapping process no map took (it holds nothing). Run before multiprocessing's own
    exit handler (registered earlier, run later), whose SIGTERM would reach a spare still importing pycolmap,
    whose signal handler (glog's) prints a stack trace for it."""
    with _spare_lock:
        spare = _spare
    if spare is not None and spare.process.is_alive():
        spare.process.kill()
        spare.process.join()


def _spawned() -> _Spawned:
    """The process ``prepare`` spawned, if it still runs, else a new one."""
    global _spare
    with _spare_lock:
        spare, _spare = _spare, None
    return spare if spare is not None and spare.process.is_alive() else _Spawned()


class MappingProcess:
    """``LocalMapper`` of ``slam_map``'s copy in a spawned process (``prepare``'s, or a new one); camera
    intrinsics ``K`` (3, 3), image ``size`` (w, h). Raises ``MappingProcessError`` when the process does not
    come up."""

    def __init__(self, slam_map: MapDatabase, K: np.ndarray, size: tuple[int, int], settings: SlamSettings):
        self.map = slam_map
        self._local = LocalMapper(slam_map, K, size, settings, threaded=False)
        spawned = _spawned()
        self._inbox, self._process, self._received = spawned.inbox, spawned.process, spawned.received
        self._inbox.put(("camera", np.asarray(K, np.float64), size, settings, slam_map.scale_factor, slam_map.levels))
        self._pending: list[int] = []
        self._alive = True
        self.history: list[MappedKeyframe] = []
        """Every keyframe mapped so far, oldest first."""
        self.focal_check: FocalCheck | None = None
        """The mapping process's check of the camera matrix, once it came back."""
        sync.record_counts(slam_map)
        self._wait_ready()
        if slam_map.keyframes:
            self._reset()

    def _wait_ready(self) -> None:
        try:
            message = pickle.loads(self._received.get(timeout=START_TIMEOUT_S))
        except queue.Empty:
            self._process.kill()
            raise MappingProcessError(f"the mapping process did not start within {START_TIMEOUT_S:.0f} s") from None
        if message == ("ready",):
            return
        self._process.kill()
        if message[0] == "ended":
            raise MappingProcessError(
                f"the mapping process ended at its start (exit code {self._process.exitcode}): a script that makes "
                "a SlamSystem must keep its top level under `if __name__ == \"__main__\":` (the process imports it "
                "again), or map on a thread (mapping=\"thread\")")
        raise MappingProcessError(f"the mapping process said {message!r} instead of being ready")

    @property
    def idle(self) -> bool:
        """No keyframe sent and not mapped yet (after bringing in what has come back)."""
        self.sync()
        return not self._pending

    def wait_idle(self, timeout_s: float) -> bool:
        """Bring in every change that comes back until each keyframe sent is mapped (True), at most
        ``timeout_s`` seconds (False). A mapping process that is gone has nothing pending."""
        deadline = time.monotonic() + timeout_s
        self.sync()
        while self._pending:
            try:
                message = self._received.get(timeout=max(deadline - time.monotonic(), 0.0))
            except queue.Empty:
                return False
            self._receive(pickle.loads(message))
        return True

    def enqueue(self, keyframe_id: int) -> None:
        """Send the tracker's new keyframe ``keyframe_id`` (and the counters since the last message)."""
        if not self._alive:
            return
        with self.map.lock:
            keyframe = self.map.keyframes[keyframe_id]
            message = ("keyframe", keyframe.id, keyframe.stamp_ns, keyframe.T_camera_world.copy(), keyframe.features,
                       keyframe.point_ids.copy(), sync.take_counts(self.map))
        self._pending.append(keyframe_id)
        self._inbox.put(message)

    def adjust_initial_map(self, first: int, second: int) -> None:
        """Bundle adjust a new map's first two keyframes here (the tracker waits for it, as it must),
        then send the map over."""
        self._local.adjust_initial_map(first, second)
        self._reset()

    def resend(self) -> None:
        """Send the whole map over, as the tracker changed it (``bridging``) while this process was idle."""
        self._reset()

    def sync(self) -> None:
        """Bring in every mapped keyframe's changes that came back (never waits)."""
        while self._alive:
            try:
                message = self._received.get_nowait()
            except queue.Empty:
                return
            self._receive(pickle.loads(message))

    def close(self) -> None:
        """Let the process map the keyframes it was given, bring their changes in, and end it."""
        if self._alive:
            self._inbox.put(("stop", sync.take_counts(self.map)))
        while self._alive:
            try:
                self._receive(pickle.loads(self._received.get(timeout=STOP_TIMEOUT_S)))
            except queue.Empty:
                self._gone(f"it did not stop within {STOP_TIMEOUT_S:.0f} s")
        self._process.join(timeout=STOP_TIMEOUT_S)
        if self._process.is_alive():
            self._process.kill()
            self._process.join()

    def _gone(self, why: str) -> None:
        logger.error("local mapping stopped: %s; tracking goes on with the map as it is", why)
        self._pending.clear()
        self._alive = False

    def _reset(self) -> None:
        with self.map.lock:
            snapshot = sync.snapshot(self.map)
            sync.take_counts(self.map)
        self._pending.clear()
        self._inbox.put(("reset", snapshot))

    def _receive(self, message: tuple[Any, ...]) -> None:
        kind = message[0]
        if kind == "points":
            sync.apply_changes(self.map, message[1], self._pending)
        elif kind == "mapped":
            _, keyframe_id, changes, record = message
            if keyframe_id in self._pending:
                self._pending.remove(keyframe_id)
            sync.apply_changes(self.map, changes, self._pending)
            self.history.append(record)
        elif kind == "calibration":
            self.focal_check = message[1]
        elif kind == "stopped":
            sync.apply_changes(self.map, message[1], [])
            self._pending.clear()
            self._alive = False
        elif kind in ("failed", "ended"):
            self._gone(message[1])


def _start_deaf_to_ctrl_c(process: Any) -> None:
    """Start ``process`` with SIGINT ignored from its first instruction on (an ignored signal stays ignored
    across the spawn's exec, and Python then installs no KeyboardInterrupt handler), so a Ctrl-C to the whole
    process group while it still imports NumPy and pycolmap leaves it be: its tracker ends it. Only the main
    thread may set a handler; a node on another thread (in a process group) blocks SIGINT in its own thread
    while it starts the process instead, and a blocked signal stays blocked across the exec too."""
    if threading.current_thread() is not threading.main_thread():
        blocked = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
        try:
            process.start()
        finally:
            signal.pthread_sigmask(signal.SIG_SETMASK, blocked)
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        process.start()
    finally:
        signal.signal(signal.SIGINT, previous)


def _camera(inbox: Any) -> tuple[Any, ...] | None:
    """The ``camera`` message's fields, waited for (None once the parent is gone)."""
    parent = multiprocessing.parent_process()
    while True:
        try:
            message = inbox.get(timeout=PARENT_CHECK_S)
        except queue.Empty:
            if parent is not None and not parent.is_alive():
                return None
            continue
        if message[0] == "camera":
            return tuple(message[1:])


def _serve(inbox: Any, writer: Any) -> None:
    """The mapping process: its camera, then keyframes in, changes out, until ``stop`` or the parent's end.
    SIGTERM ends it quietly: importing pycolmap installed glog's handler, which prints a stack trace for it."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)

    def send(*message: Any) -> None:
        writer.send_bytes(pickle.dumps(message, pickle.HIGHEST_PROTOCOL))

    parent = multiprocessing.parent_process()
    camera = _camera(inbox)
    if camera is None:
        return
    K, size, settings, scale_factor, levels = camera
    slam_map = MapDatabase(scale_factor, levels)
    sync.record_changes(slam_map)
    mapper = LocalMapper(slam_map, K, size, settings, threaded=False)
    waiting: list[int] = []
    stopping = checked = False
    send("ready")
    try:
        while True:
            try:
                message = inbox.get(timeout=PARENT_CHECK_S) if not waiting and not stopping else inbox.get_nowait()
            except queue.Empty:
                message = None
            if message is not None:
                stopping |= _take(message, slam_map, waiting)
                continue
            if waiting:
                keyframe_id = waiting.pop(0)
                mapper.process(keyframe_id, others_waiting=bool(waiting),
                               stepped=lambda: send("points", sync.take_changes(slam_map)))
                if mapper.focal_check is not None and not checked:
                    checked = True
                    send("calibration", mapper.focal_check)
                send("mapped", keyframe_id, sync.take_changes(slam_map),
                     dataclasses.replace(mapper.history.pop(), waiting=len(waiting)))
            elif stopping:
                send("stopped", sync.take_changes(slam_map))
                return
            elif parent is not None and not parent.is_alive():
                return
    except (BrokenPipeError, EOFError):
        return  # the tracker is gone
    except Exception as error:
        logger.exception("local mapping failed")
        send("failed", f"{type(error).__name__}: {error}")


def _take(message: tuple[Any, ...], slam_map: MapDatabase, waiting: list[int]) -> bool:
    """Apply one message from the tracker; True for ``stop``."""
    kind = message[0]
    if kind == "reset":
        sync.restore(slam_map, message[1])
        waiting.clear()
    elif kind == "keyframe":
        _, keyframe_id, stamp_ns, T, features, point_ids, counts = message
        sync.add_counts(slam_map, counts)
        if keyframe_id not in slam_map.keyframes:
            slam_map.add_keyframe(stamp_ns, T, features, point_ids, keyframe_id=keyframe_id)
        waiting.append(keyframe_id)
    elif kind == "stop":
        sync.add_counts(slam_map, message[1])
        return True
    return False
