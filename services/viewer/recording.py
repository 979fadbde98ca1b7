"""The Rerun recording the viewer writes: its sinks, and logging a ``Scene`` into it.

Sinks (one recording, either or both): an ``.rrd`` file (``rr.FileSink``), and a gRPC server
that Rerun viewers connect to later (``rr.GrpcServerSink``) with
``rerun rerun+http://HOST:PORT/proxy``. The server keeps up to ``memory_limit`` of the
recording for viewers that connect late, dropping the oldest data beyond it.

Binding: ``rr.serve_grpc`` always binds 0.0.0.0, every interface of the machine, and the
server has no authentication. Here the address is a setting that defaults to 127.0.0.1
(this machine only; reach it from elsewhere through an SSH tunnel); bind 0.0.0.0 only on a
network you trust.

Time: Rerun keeps the current time per thread. ``ViewLog.log`` sets the ``stamp`` and
``seq`` timelines (see ``services.viewer.layout``) right before it logs a message's rows, on
the calling thread; use one ``ViewLog`` from one thread.
"""

from __future__ import annotations

import socket
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import rerun as rr

from protocol.message import Message
from services.viewer import layout
from services.viewer.blueprint import blueprint
from services.viewer.scene import Row, Scene, frame_seq

APPLICATION_ID = "artrack"


class SinkError(ValueError):
    """A sink that cannot be opened: the message says which and why."""


@dataclass(frozen=True)
class Serve:
    """A gRPC server for Rerun viewers: address, port, and how much it keeps for late viewers."""

    port: int
    bind: str = "127.0.0.1"
    memory_limit: str = "1GiB"

    @property
    def url(self) -> str:
        return f"rerun+http://{self.bind}:{self.port}/proxy"


def open_recording(name: str, *, out: Path | None = None, serve: Serve | None = None,
                   recording_id: str | None = None) -> rr.RecordingStream:
    """A recording called ``name`` streaming to ``out`` and/or a gRPC server (at least one)."""
    if out is None and serve is None:
        raise SinkError("nothing to write to: give an .rrd file, a gRPC server, or both")
    sinks: list[rr.FileSink | rr.GrpcServerSink] = []
    if out is not None:
        if not out.parent.is_dir():
            raise SinkError(f"cannot write {out}: {out.parent} is not a folder")
        sinks.append(rr.FileSink(str(out)))
    if serve is not None:
        _check_free(serve)
        sinks.append(rr.GrpcServerSink(bind_ip=serve.bind, port=serve.port, server_memory_limit=serve.memory_limit))
    recording = rr.RecordingStream(APPLICATION_ID, recording_id=recording_id)
    recording.set_sinks(*sinks)
    recording.send_recording_name(name)
    return recording


def _check_free(serve: Serve) -> None:
    """Fail now, with a clear message, when the server could not bind (Rerun would only log it)."""
    try:
        with socket.create_server((serve.bind, serve.port)):
            pass
    except OSError as exc:
        raise SinkError(f"cannot serve Rerun on {serve.bind}:{serve.port}: {exc.strerror or exc}") from exc


class ViewLog:
    """Logs each message's rows at its time, and keeps the blueprint in step with the cameras.

    ``rows`` counts the rows logged so far. Closing flushes and disconnects every sink (the
    file is complete afterwards).
    """

    def __init__(self, recording: rr.RecordingStream, scene: Scene):
        self.recording = recording
        self.scene = scene
        self.rows = 0
        self._blueprint_cameras = -1
        self._log(scene.setup())
        self._update_blueprint()

    def __enter__(self) -> ViewLog:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def log(self, message: Message) -> int:
        """Log what draws ``message``; return how many rows that was."""
        rows = self.scene.rows(message)
        if rows:
            self.recording.reset_time()
            self.recording.set_time(layout.STAMP, timestamp=np.datetime64(message.header.stamp_ns, "ns"))
            seq = frame_seq(message)
            if seq is not None:
                self.recording.set_time(layout.SEQ, sequence=seq)
            self._log(rows)
        self._update_blueprint()
        return len(rows)

    def _log(self, rows: list[Row]) -> None:
        for row in rows:
            self.recording.log(row.entity, *row.archetypes, static=row.static)
        self.rows += len(rows)

    def _update_blueprint(self) -> None:
        if len(self.scene.cameras) != self._blueprint_cameras:
            self.recording.send_blueprint(blueprint(self.scene.cameras), make_active=True, make_default=True)
            self._blueprint_cameras = len(self.scene.cameras)

    def close(self) -> None:
        self.recording.flush()
        self.recording.disconnect()
