"""The bench process's end of the link: the spawned sink process and a Zenoh session connected to it.

The sink listens on a free loopback port (found by binding ``127.0.0.1:0``); the bench
process's session connects to it, peer to peer, multicast scouting off, no router. Closing a
``Sink`` (it is a context manager) closes the session and stops the process, killing it if it
does not quit within ``QUIT_S``, whatever happened before.
"""

from __future__ import annotations

import json
import queue
import socket
import subprocess
import sys
import threading
from pathlib import Path
from typing import Any

import zenoh

from services.client.transport import session_config
from tests.bench.sink import REPLY

ROOT = Path(__file__).resolve().parents[2]
REPLY_S = 30.0
QUIT_S = 5.0


class BenchError(RuntimeError):
    """The sink died, did not answer in time, or reported a fault."""


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


class Sink:
    """A running sink process and the bench process's session connected to it."""

    def __init__(self) -> None:
        endpoint = f"tcp/127.0.0.1:{free_port()}"
        self._process = subprocess.Popen([sys.executable, "-m", "tests.bench.sink", endpoint], cwd=ROOT,
                                         stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        self._replies: queue.Queue[dict[str, Any] | None] = queue.Queue()
        threading.Thread(target=self._pump, daemon=True).start()
        self.session: zenoh.Session | None = None
        try:
            self._reply()
            self.session = zenoh.open(session_config("peer", connect=(endpoint,)))
        except BaseException:
            self.close()
            raise

    def __enter__(self) -> Sink:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def start(self, key: str, reader: dict[str, Any]) -> None:
        """Have the sink subscribe to ``key`` and read each sample as ``reader`` says."""
        self._command({"cmd": "start", "key": key, "reader": reader})

    def stop(self, sent: int) -> dict[str, Any]:
        """Tell the sink ``sent`` messages went out; its report once they arrived (see ``sink``)."""
        report = self._command({"cmd": "stop", "sent": sent})
        if report["refused"]:
            raise BenchError(f"the sink could not read {report['refused']} of {sent} messages")
        return report

    def close(self) -> None:
        if self.session is not None:
            self.session.close()
            self.session = None
        if self._process.poll() is None:
            try:
                self._send({"cmd": "quit"})
                self._process.wait(QUIT_S)
            except (OSError, subprocess.TimeoutExpired):
                self._process.kill()
                self._process.wait()

    def _command(self, command: dict[str, Any]) -> dict[str, Any]:
        try:
            self._send(command)
        except OSError as exc:
            raise BenchError(f"the sink is gone (code {self._process.poll()})") from exc
        answer = self._reply()
        if "error" in answer:
            raise BenchError(answer["error"])
        return answer

    def _send(self, command: dict[str, Any]) -> None:
        assert self._process.stdin is not None
        self._process.stdin.write(json.dumps(command) + "\n")
        self._process.stdin.flush()

    def _reply(self) -> dict[str, Any]:
        try:
            answer = self._replies.get(timeout=REPLY_S)
        except queue.Empty:
            raise BenchError(f"the sink did not answer within {REPLY_S:.0f} s") from None
        if answer is None:
            raise BenchError(f"the sink exited (code {self._process.wait()})")
        return answer

    def _pump(self) -> None:
        """Queue the sink's replies; pass anything else it prints on to stderr."""
        assert self._process.stdout is not None
        for line in self._process.stdout:
            if line.startswith(REPLY):
                self._replies.put(json.loads(line[len(REPLY):]))
            else:
                sys.stderr.write(line)
        self._replies.put(None)
