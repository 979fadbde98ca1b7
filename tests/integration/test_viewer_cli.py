"""``artrack view IN.mcap OUT.rrd`` as a process: on what ``artrack record`` recorded from a live rig, on damage."""

from __future__ import annotations

import os
import signal

import numpy as np
import pytest

from protocol import Header, Image, decode, encode
from services.recorder.reading import EXIT_DAMAGED, Scan
from services.recorder.writing import RecordingWriter
from tests.viewer_contents import RrdContents

from .support import START_S, start_node, states, wait_live, wait_until

pytestmark = pytest.mark.integration

FRAMES, FPS, WIDTH, HEIGHT = 30, 30, 160, 120


@pytest.fixture
def recorded(bus, procs, session, tmp_path):
    """A recording by ``artrack record`` of ``synthetic:markers`` (images, calibration, ground truth)."""
    path = tmp_path / "run.mcap"
    recorder = procs.artrack("record", str(path), name="recorder")
    wait_live(session, bus.keys, {"recorder"}, [recorder])
    capture = start_node(procs, "capture", "cam", source="synthetic:markers", fps=FPS, frames=FRAMES,
                         wait_for_subscriber=True, scene={"width": WIDTH, "height": HEIGHT})
    assert capture.wait(START_S + FRAMES / FPS) == 0, capture.describe()
    # Calibration and ground truth travel as results (never dropped): 2 per frame at least.
    wait_until(lambda: (s := states(session, bus.keys).get("recorder")) and s.received >= 2 * FRAMES,
               START_S, "the recorder to receive every result")
    os.kill(recorder.pid, signal.SIGINT)
    assert recorder.wait(15) == 0, recorder.describe()
    return path


def recorded_images(path) -> list[Image]:
    return [decode(r.message.data) for r in Scan(path).messages() if r.channel.topic.endswith("/cam0/image")]


def test_view_draws_a_recording_as_the_live_viewer_does(recorded, procs, tmp_path):
    full, small = tmp_path / "full.rrd", tmp_path / "small.rrd"
    assert procs.run("view", str(recorded), str(full)).poll() == 0
    done = procs.run("view", str(recorded), str(small), "--image-hz", "10", "--jpeg", "80")
    assert done.poll() == 0 and "wrote" in done.stderr, done.describe()

    images = recorded_images(recorded)
    contents = RrdContents(full)
    logged = contents.rows("world/cam0/image", "Image:buffer")
    assert len(logged) == len(images) > FRAMES // 2  # offline: every recorded frame
    np.testing.assert_array_equal(logged[-1].numbers(), images[-1].data.ravel())
    assert [row.times["stamp"] for row in logged] == [image.header.stamp_ns for image in images]
    assert contents.rows("world/cam0/image", "Pinhole:resolution")[0].numbers().tolist() == [WIDTH, HEIGHT]
    truth = [e for e in contents.entities if e.startswith("world/cam0/truth/marker/")]
    assert truth and all(f"world/cam0/trajectory/truth/{e.split('/truth/')[1]}" in contents.entities for e in truth)

    limited = RrdContents(small).rows("world/cam0/image", "EncodedImage:blob")
    assert 0 < len(limited) <= FRAMES * 10 / FPS + 1 < len(images)


def test_view_exit_codes_say_what_went_wrong(procs, tmp_path):
    whole, cut = tmp_path / "whole.mcap", tmp_path / "cut.mcap"
    writer = RecordingWriter(whole)
    for i in range(40):
        frame = Image(header=Header(stamp_ns=i * 33_333_333, frame_id="cam0", seq=i), encoding="mono8",
                      data=np.random.default_rng(i).integers(0, 256, (HEIGHT, WIDTH), dtype=np.uint8))
        writer.write("ar/lab/cam0/image", encode(frame), i)
        if i % 10 == 9:
            writer.flush()
    writer.close()
    cut.write_bytes(whole.read_bytes()[: whole.stat().st_size // 2])
    damaged = procs.run("view", str(cut), str(tmp_path / "cut.rrd"))
    assert damaged.poll() == EXIT_DAMAGED and "damaged" in damaged.stderr, damaged.describe()
    assert 0 < len(RrdContents(tmp_path / "cut.rrd").rows("world/cam0/image", "Image:buffer")) < 40
    missing = procs.run("view", str(tmp_path / "none.mcap"), str(tmp_path / "none.rrd"))
    assert missing.poll() == 2 and "none.mcap" in missing.stderr
    assert not (tmp_path / "none.rrd").exists()
    before = (tmp_path / "cut.rrd").read_bytes()
    kept = procs.run("view", str(whole), str(tmp_path / "cut.rrd"))
    assert kept.poll() == 2 and kept.stderr.strip().endswith(f"{tmp_path / 'cut.rrd'} exists: give --force to "
                                                              "overwrite it"), kept.describe()
    assert (tmp_path / "cut.rrd").read_bytes() == before
    forced = procs.run("view", str(whole), str(tmp_path / "cut.rrd"), "--force")
    assert forced.poll() == 0, forced.describe()
    assert len(RrdContents(tmp_path / "cut.rrd").rows("world/cam0/image", "Image:buffer")) == 40
