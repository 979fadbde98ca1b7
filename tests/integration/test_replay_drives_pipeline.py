"""A replayed session drives a pipeline exactly as the live session did."""

from __future__ import annotations

import pytest

from .support import START_S, live_names, start_node, states, wait_until
from .test_recorder_bus import channels, recorder_stats, stop

pytestmark = pytest.mark.integration

FRAMES = 24


def run_echo_and_record(bus, procs, session, out, feed, expected: int) -> dict[str, list[bytes]]:
    """Start an echo node (queueing every frame) and a recorder of the camera's keys, ``feed()``,
    wait for the recorder to have ``expected`` messages, return the recording."""
    echo = start_node(procs, "echo", "echo", camera="cam0", depth=FRAMES)
    recorder = procs.artrack("record", str(out), "--keys", "cam0/*", name=f"record-{out.stem}")
    wait_until(lambda: {"echo", "recorder"} <= live_names(session, bus.keys), START_S, "echo and recorder up")
    feed()
    wait_until(lambda: _relayed(session, bus) >= FRAMES, START_S, "the echo node to relay every frame")
    wait_until(lambda: recorder_stats(session, bus.keys, expected), START_S, f"{expected} messages recorded")
    stop(recorder)
    stop(echo)
    return channels(out)


def _relayed(session, bus) -> int:
    echo = states(session, bus.keys).get("echo")
    return 0 if echo is None else echo.published


def test_pipeline_outputs_on_replay_equal_those_of_the_live_run(bus, procs, session, tmp_path):
    live_file, replay_file = tmp_path / "live.mcap", tmp_path / "replayed.mcap"

    def capture() -> None:
        cam = start_node(procs, "capture", "cam", source="synthetic:markers", cameras=["cam0"], frames=FRAMES,
                         fps=20, scene={"noise_std": 2.0}, wait_for_subscriber=True,
                         flow={"lossless": True})  # frames block rather than drop on a busy bus
        assert cam.wait(3 * START_S) == 0, cam.describe()

    live = run_echo_and_record(bus, procs, session, live_file, capture, 4 * FRAMES)  # image, info, truth, echo
    image_key, echo_key = bus.keys.image("cam0"), bus.keys.echo("cam0")
    assert len(live[image_key]) == len(live[echo_key]) == FRAMES

    def replay() -> None:
        player = procs.artrack("replay", str(live_file), "--keys", "cam0/image", "--wait", str(START_S),
                               name="replay")
        assert player.wait(3 * START_S) == 0, player.describe()

    replayed = run_echo_and_record(bus, procs, session, replay_file, replay, 2 * FRAMES)  # image, echo
    assert replayed[image_key] == live[image_key]  # the same inputs, byte for byte, in the same order
    assert replayed[echo_key] == live[echo_key]  # so the same outputs
