"""The test tiers hold themselves (``tiers`` in tests/conftest.py): a test not marked ``integration``
fails the moment it starts a process or opens a Zenoh session, whichever way it tries."""

import multiprocessing
import os
import subprocess
import sys

import pytest

REFUSED = "is not marked integration"


@pytest.mark.parametrize("start", [
    lambda: subprocess.run(["true"], check=False),
    lambda: subprocess.Popen([sys.executable, "-c", "pass"]),
    lambda: multiprocessing.get_context("spawn").Process(target=print).start(),
    lambda: multiprocessing.get_context("fork").Process(target=print).start(),
    lambda: os.system("true"),
    lambda: os.posix_spawn("/bin/true", ["true"], {}),
    lambda: os.fork(),
], ids=["subprocess.run", "Popen", "spawn", "fork", "os.system", "posix_spawn", "os.fork"])
def test_a_unit_test_that_starts_a_process_fails(start):
    with pytest.raises(pytest.fail.Exception, match=f"starts a process .* {REFUSED}"):
        start()


def test_a_unit_test_that_opens_a_zenoh_session_fails():
    from services.bus.session import BusConfig, open_session

    with pytest.raises(pytest.fail.Exception, match=f"opens a Zenoh session but {REFUSED}"):
        open_session(BusConfig(connect=("tcp/127.0.0.1:9",), autostart_router=False))
