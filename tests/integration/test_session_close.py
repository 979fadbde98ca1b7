"""Closing a session whose callbacks ran on daemon threads: the process then exits with its own code, where a
callback thread still inside Zenoh as the interpreter finalised used to abort it (SIGABRT)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.integration

ROOT = Path(__file__).resolve().parents[2]

DAEMON_SUBSCRIBERS = """
import threading, time
import zenoh
from services.bus.session import close_session

config = zenoh.Config()
config.insert_json5("scouting/multicast/enabled", "false")
config.insert_json5("listen/endpoints", '["tcp/127.0.0.1:0"]')
for _ in range(20):
    session = zenoh.open(config)
    subscribers = []
    declare = lambda: subscribers.append(session.declare_subscriber("t/**", lambda sample: time.sleep(0.01)))
    thread = threading.Thread(target=declare, daemon=True)  # as a node's thread of a process group declares
    thread.start()
    thread.join()
    for _ in range(5):
        session.put("t/a", b"x")
    time.sleep(0.005)
    close_session(session)  # callbacks still queued and running
print("closed", flush=True)
raise SystemExit(3)
"""


def test_a_process_whose_daemon_threads_subscribed_exits_with_its_code_once_its_session_is_closed():
    done = subprocess.run([sys.executable, "-c", DAEMON_SUBSCRIBERS], cwd=ROOT, capture_output=True, text=True,
                          timeout=120)
    assert done.stdout == "closed\n", done.stderr[-2000:]
    assert done.returncode == 3, f"exit {done.returncode} (-6 or 134: aborted)\n{done.stderr[-2000:]}"
    assert "exception not rethrown" not in done.stderr
