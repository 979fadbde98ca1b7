"""The client app's handle on artrack: ``connect()`` and what a ``Client`` can do.

::

    from services.client import connect

    with connect() as ar:                          # same bus options as the nodes
        for update in ar.poses("cam0/**"):         # every target seen by cam0 (markers, boards)
            print(update.target, update.pose.transform.translation, f"{update.latency_ms:.1f} ms")

While connected, the client holds a liveliness token at ``keys.client(id)`` and answers a
``ClientState`` (what it subscribed to, what it got) on ``keys.client_state(id)``, so
``artrack status`` can say which apps wait for which targets.
"""

from __future__ import annotations

import os
import socket
import sys
import threading
import time
import uuid
from collections.abc import Callable
from pathlib import Path

import zenoh

from protocol.codec import encode
from protocol.keys import Keys
from protocol.message import Header
from protocol.sensors import CameraInfo
from protocol.spatial import StaticTransforms
from protocol.system import ClientState, NodeStats
from services.bus.discovery import first_answers, live_nodes, node_states
from services.bus.security import Security
from services.bus.session import close_session
from services.bus.settings import BusSettings
from services.client.streams import DEFAULT_DEPTH, AsyncPoseStream, Feed, PoseStream, PoseUpdate
from services.convert import frame_graph
from services.geometry.frames import FrameGraph

Stream = PoseStream | AsyncPoseStream


class Client:
    """A connected client app (see the module docstring). Thread-safe; close it when done."""

    def __init__(self, settings: BusSettings, *, app: str | None = None):
        self.settings = settings
        self.keys: Keys = settings.keys
        self.id = uuid.uuid4().hex[:12]
        self.app = app or Path(sys.argv[0]).stem or "python"
        self._started = time.monotonic()
        self._lock = threading.Lock()
        self._streams: list[Stream] = []
        self._callbacks: list[Feed] = []
        self._latest: dict[str, Feed] = {}
        self.session = settings.open()
        try:
            self._token = self.session.liveliness().declare_token(self.keys.client(self.id))
            self._queryable = self.session.declare_queryable(self.keys.client_state(self.id), self._on_state_query)
        except Exception:
            close_session(self.session)
            raise

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def poses(self, target: str = "**", *, idle_timeout_s: float | None = None,
              depth: int = DEFAULT_DEPTH) -> PoseStream:
        """Poses of the targets matching ``target`` (``cam0/marker/7``, ``cam0/marker/*``, ``cam0/**``, ``**``),
        in arrival order; ``*`` matches one segment, ``**`` any number.

        The iteration ends after ``idle_timeout_s`` without a pose (None: never) or on ``close``.
        """
        stream = PoseStream(self.session, self.keys, self.keys.pose_pattern(target),
                            idle_timeout_s=idle_timeout_s, depth=depth, on_close=self._forget)
        with self._lock:
            self._streams.append(stream)
        return stream

    def poses_async(self, target: str = "**", *, idle_timeout_s: float | None = None,
                    depth: int = DEFAULT_DEPTH) -> AsyncPoseStream:
        """The ``async for`` form of ``poses``; call it from inside the running event loop."""
        stream = AsyncPoseStream(self.session, self.keys, self.keys.pose_pattern(target),
                                 idle_timeout_s=idle_timeout_s, depth=depth, on_close=self._forget)
        with self._lock:
            self._streams.append(stream)
        return stream

    def on_pose(self, target: str, callback: Callable[[PoseUpdate], None]) -> Feed:
        """Call ``callback(update)`` on Zenoh's thread for every pose of ``target`` (keep it short);
        ``close()`` the returned feed to stop. A callback that raises is logged and counted."""
        feed = Feed(self.session, self.keys, self.keys.pose_pattern(target), callback, on_close=self._forget)
        with self._lock:
            self._callbacks.append(feed)
        return feed

    def latest(self, target: str, timeout_s: float = 1.0) -> PoseUpdate | None:
        """The newest pose of ``target``; the first call subscribes and waits up to ``timeout_s``.
        None when nothing has arrived (no such target, or it is not tracked)."""
        with self._lock:
            feed = self._latest.get(target)
            if feed is None:
                feed = self._latest[target] = Feed(self.session, self.keys, self.keys.pose_pattern(target),
                                                   lambda update: None)
        return feed.wait(timeout_s)

    def services(self, timeout_s: float = 0.5) -> list[tuple[str, str]]:
        """``(rig, node name)`` of every live node in the namespace (listens ``timeout_s``)."""
        return live_nodes(self.session, self.keys, timeout_s)

    def status(self, timeout_s: float = 1.0) -> dict[tuple[str, str], NodeStats]:
        """Every reachable node's health, by ``(rig, node name)``."""
        return node_states(self.session, self.keys, timeout_s)

    def calibration(self, camera: str, timeout_s: float = 1.0) -> CameraInfo | None:
        """The calibration the capture node holds for ``camera``; None when nobody answers with one."""
        found = first_answers(self.session, self.keys.calibration(camera), CameraInfo, timeout_s)
        return next(iter(found.values()), None)

    def frames(self, timeout_s: float = 1.0) -> FrameGraph:
        """The rig's static transforms, gathered from every node that answers within ``timeout_s``.

        ``graph.transform("cam0", "cam1")`` is then ``T_cam0_cam1`` (4, 4); cameras hang off the
        ``rig`` frame. Empty when nobody answers; ``FrameError`` when two nodes contradict each other.
        """
        found = first_answers(self.session, self.keys.rig_static_transforms(), StaticTransforms, timeout_s)
        return frame_graph([found[key] for key in sorted(found)])

    def state(self) -> ClientState:
        """What this client subscribed to and what it received, as ``artrack status`` sees it."""
        with self._lock:
            subscriptions = [s.state() for s in self._streams]
            subscriptions += [feed.state() for feed in [*self._callbacks, *self._latest.values()]]
        return ClientState(header=Header(stamp_ns=time.time_ns()), client=self.id, app=self.app,
                           host=socket.gethostname(), pid=os.getpid(), uptime_s=time.monotonic() - self._started,
                           subscriptions=tuple(subscriptions))

    def _on_state_query(self, query: zenoh.Query) -> None:
        query.reply(self.keys.client_state(self.id), encode(self.state()))

    def _forget(self, closed: Stream | Feed) -> None:
        with self._lock:
            if isinstance(closed, Feed):
                if closed in self._callbacks:
                    self._callbacks.remove(closed)
            elif closed in self._streams:
                self._streams.remove(closed)

    def close(self) -> None:
        """Stop every stream and callback, leave the bus."""
        with self._lock:
            streams, feeds = list(self._streams), [*self._callbacks, *self._latest.values()]
            self._callbacks.clear()
            self._latest.clear()
        for stream in streams:
            stream.close()
        for feed in feeds:
            feed.close()
        self._queryable.undeclare()
        self._token.undeclare()
        close_session(self.session)


def connect(*, mode: str | None = None, connect: tuple[str, ...] | list[str] | str | None = None,
            listen: tuple[str, ...] | list[str] | None = None, zenoh_config: str | Path | None = None,
            namespace: str | None = None, rig: str | None = None, app: str | None = None,
            security: Security | None = None) -> Client:
    """Join the bus as a client app. Arguments left out come from the same environment variables
    the nodes read (``ARTRACK_MODE``, ``ARTRACK_CONNECT``, ``ZENOH_CONFIG``, ``ARTRACK_RIG``,
    ``ARTRACK_TLS_ROOT_CA``, ``ARTRACK_USER``, ...), else the defaults: a peer that meets the nodes
    through the local router on ``tcp/127.0.0.1:7447``. ``security`` (TLS files, user and
    password) replaces whatever the environment said about them.

    Raises ``BusError`` naming the endpoint when the session cannot be opened (for example a
    client-mode session whose router is down, or that the router refused), ValueError for
    settings that cannot work (credentials in peer mode, a ``tls/`` endpoint without a root CA).
    """
    if isinstance(connect, str):
        connect = (connect,)
    settings = BusSettings.from_env(mode=mode, connect=tuple(connect or ()), listen=tuple(listen or ()),
                                    zenoh_config=zenoh_config, namespace=namespace, rig=rig, security=security)
    return Client(settings, app=app)
