"""640x480 images from another process arrive intact through the publisher's shared memory, and
as ordinary bytes when the publisher's session has shared memory disabled.

Zenoh's implicit copy of large payloads into its own pool is off in the publisher's config, so an
image that arrives in shared memory was written there by the publisher itself."""

from __future__ import annotations

import json
import threading
import time

import pytest
import zenoh

from protocol.codec import decode
from services.bus.pubsub import Role
from services.bus.session import open_session
from services.bus.shm import received_bytes

from .busprobe import make_message
from .support import START_S, probe_argv, published, wait_until

pytestmark = pytest.mark.integration

COUNT = 6
WIDTH, HEIGHT = 640, 480


def _config_file(tmp_path, router: str, shared_memory: bool) -> str:
    """A Zenoh config for the probe: a peer of the test's router, with shared memory on or off and
    Zenoh's implicit use of it off."""
    path = tmp_path / "probe-zenoh.json5"
    path.write_text(json.dumps({
        "mode": "peer",
        "connect": {"endpoints": [router]},
        "listen": {"endpoints": ["tcp/127.0.0.1:0"]},
        "scouting": {"multicast": {"enabled": False}},
        "transport": {"shared_memory": {"enabled": shared_memory, "transport_optimization": {"enabled": False}}},
    }))
    return str(path)


@pytest.mark.parametrize("shared_memory", [True, False], ids=["shm", "shm-disabled"])
def test_images_arrive_intact_through_shared_memory_or_without_it(bus, procs, tmp_path, shared_memory):
    session = open_session(bus.config)
    arrived: list[tuple[bool, bytes]] = []
    lock = threading.Lock()

    def on_sample(sample: zenoh.Sample) -> None:
        with lock:
            arrived.append((sample.payload.as_shm() is not None, received_bytes(sample.payload)))

    try:
        key = f"{bus.keys.prefix}/probe/image"
        subscriber = session.declare_subscriber(key, on_sample)
        probe = procs.start(
            probe_argv("image", str(COUNT), "--key", key, "--role", Role.RESULT.value, "--rate", "20",
                       "--peer", str(session.info.zid()), "--width", str(WIDTH), "--height", str(HEIGHT)),
            name="publish-image", env={"ZENOH_CONFIG": _config_file(tmp_path, bus.endpoint, shared_memory)})
        assert wait_until(lambda: published(probe), START_S + 20.0, "the probe to publish") == COUNT
        wait_until(lambda: len(arrived) >= COUNT, 10.0, f"{COUNT} images")
        time.sleep(0.2)
        subscriber.undeclare()
        assert probe.wait(10) == 0, probe.describe()
    finally:
        session.close()

    assert len(arrived) == COUNT, f"{len(arrived)} images arrived, {COUNT} were sent"
    assert [in_shm for in_shm, _ in arrived] == [shared_memory] * COUNT
    for index, (_, payload) in enumerate(arrived):
        assert decode(payload) == make_message("image", index, WIDTH, HEIGHT), f"image {index} changed on the way"
