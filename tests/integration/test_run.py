"""``artrack run``: a whole job in processes, recorded, ending with its finite source."""

import dataclasses
import tomllib

import cv2
import numpy as np
import pytest
from mcap.reader import make_reader

from protocol import decode
from protocol.sensors import Image
from services.bus.pubsub import Inbox, Role
from services.calibration.camera_info import write_camera_info
from services.calibration.rig import Rig, write_rig
from services.geometry.camera import CameraModel
from services.recorder.info import summarise
from services.synthetic import make_scene
from tests.integration.support import ROOT, START_S, collect
from tests.viewer_contents import RrdContents

pytestmark = pytest.mark.integration

RECORDINGS = ROOT / "recordings"


def test_run_records_a_finite_job_and_exits_cleanly(procs, tmp_path):
    out = tmp_path / "job.mcap"
    job = procs.artrack("run", "echo", "--source", "synthetic:markers", "--frames", "20", "--fps", "30",
                        "--record", str(out), name="job")
    assert job.wait(3 * START_S) == 0, job.describe()
    with open(out, "rb") as f:
        reader = make_reader(f)
        counts: dict[str, int] = {}
        images, echoes = [], []
        for _, channel, message in reader.iter_messages():
            stream = channel.topic.rsplit("/", 1)[-1]
            counts[stream] = counts.get(stream, 0) + 1
            if channel.topic.endswith("/cam0/image"):
                images.append(decode(message.data))
            elif channel.topic.endswith("/cam0/echo"):
                echoes.append(decode(message.data))
    assert counts["image"] == counts["camera_info"] == counts["truth"] == 20, counts
    assert [m.header.seq for m in images] == list(range(20))
    assert {m.header.seq for m in echoes} <= set(range(20)) and len(echoes) >= 15, len(echoes)
    assert all(e == images[e.header.seq] for e in echoes)  # relayed untouched


def test_run_refuses_an_unknown_pipeline_before_starting(procs):
    job = procs.artrack("run", "teleport", "--source", "synthetic:pattern", name="job")
    assert job.wait(START_S) == 2
    assert "unknown tracker 'teleport' (known: capture, echo, features, marker, slam, stereo)" in job.stderr



def test_run_with_rerun_writes_a_recording_rerun_reads_back(procs, tmp_path):
    out = tmp_path / "job.rrd"
    job = procs.artrack("run", "capture", "--source", "synthetic:pattern", "--frames", "12", "--fps", "20",
                        "--rerun", str(out), name="job")
    assert job.wait(3 * START_S) == 0, job.describe()
    contents = RrdContents(out)
    images = contents.rows("world/cam0/image", "Image:buffer")
    assert 3 <= len(images) <= 12, len(images)  # 0.6 s of frames at the default 10 Hz image limit
    assert contents.rows("world/cam0/image", "Pinhole:image_from_camera")


def test_run_takes_a_pipeline_file_as_one_job(procs, session, bus, tmp_path):
    """The other way round: a file `artrack up` runs is accepted by `artrack run`, which starts its source
    last and ends when the source does."""
    path = tmp_path / "echo.toml"
    path.write_text('[nodes.cam]\nkind = "capture"\nsource = ["synthetic:pattern"]\nframes = 15\nfps = 30\n'
                    'scene = { width = 64, height = 64 }\n\n[nodes.echo]\nkind = "echo"\ncamera = "cam0"\n')
    echoed = Inbox(session, bus.keys.echo("cam0"), Image, Role.RESULT, depth=100)
    job = procs.artrack("run", str(path), name="job")
    assert job.wait(3 * START_S) == 0, job.describe()
    seqs = [image.header.seq for image in collect(echoed, 10)]
    assert seqs == sorted(seqs) and set(seqs) <= set(range(15))


@pytest.mark.parametrize(("options", "expected"), [
    (["--record", "{existing}"], "nodes.recorder: {existing} exists"),
    (["--record", "/no/such/folder/x.mcap"], "nodes.recorder: cannot record to /no/such/folder/x.mcap"),
    (["--rerun", "/no/such/folder/x.rrd"], "nodes.viewer: cannot write /no/such/folder/x.rrd"),
    (["--dictionary", "DICT_FOO"], "nodes.marker-cam0: unknown marker dictionary 'DICT_FOO'"),
    (["--board", "/no/such/board.yaml"], "nodes.marker-cam0: /no/such/board.yaml: cannot read"),
    (["--calib", "/no/such/cam0.yaml"], "nodes.capture: /no/such/cam0.yaml: cannot read"),
])
def test_run_refuses_what_its_nodes_could_not_start_with_before_starting_any(procs, tmp_path, options, expected):
    existing = tmp_path / "taken.mcap"
    existing.write_bytes(b"")
    options = [o.format(existing=existing) for o in options]
    job = procs.run("run", "marker", "--source", "synthetic:markers", "--frames", "5", "--marker-length", "0.05",
                    *options)
    assert job.poll() == 2, job.describe()
    lines = [line for line in job.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and expected.format(existing=existing) in lines[0], job.stderr


def test_run_refuses_a_camera_that_does_not_open_before_saying_it_runs(procs):
    job = procs.run("run", "marker", "--source", "camera:97", "--marker-length", "0.05")
    assert job.poll() == 2, job.describe()
    lines = [line for line in job.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and "nodes.capture: camera:97: cannot open video device 97" in lines[0], job.stderr


WRONG_SIZE = "calibrated for 1280x720, the frames are 640x480 (another aspect ratio): use a calibration made at 640x480"


@pytest.mark.parametrize(("options", "expected"), [
    (["marker", "--source", "recording:{recordings}/markers.mcap", "--marker-length", "0.05",
      "--marker-pose-calib", "{hd}"], "job: nodes.marker-cam0: {hd}: " + WRONG_SIZE),
    (["marker", "--source", "synthetic:markers", "--frames", "5", "--marker-length", "0.05", "--calib", "{hd}"],
     "job: nodes.capture: {hd}: " + WRONG_SIZE),
    (["features", "--source", "synthetic:planar_target", "--frames", "5", "--target", "synthetic:planar_target",
      "--features-calib", "{hd}"], "job: nodes.features-cam0: {hd}: " + WRONG_SIZE),
    (["slam", "--source", "images:{images}", "--slam-calib", "{hd}"], "job: nodes.slam-cam0: {hd}: " + WRONG_SIZE),
    (["stereo", "--source", "recording:{recordings}/ir_rig.mcap", "--rig-file", "{rig}"],
     "job: nodes.bodies: {rig}: camera cam0 is calibrated for 1280x960, its frames are 640x480"),
], ids=["marker-pose-calib", "calib", "features-calib", "slam-calib", "rig-file"])
def test_run_refuses_a_calibration_made_for_other_frames_before_starting(procs, tmp_path, options, expected):
    """Every calibration option, the capture's and a node's own, is held against the size of the source's frames
    before any process starts (each of these sources sends 640x480 frames)."""
    hd, rig, images = tmp_path / "hd.yaml", tmp_path / "rig.yaml", tmp_path / "images"
    K = np.array([[900.0, 0.0, 639.5], [0.0, 900.0, 359.5], [0.0, 0.0, 1.0]])
    write_camera_info(hd, CameraModel("cam0", 1280, 720, K, np.zeros(5), np.eye(4)))
    doubled = np.diag([2.0, 2.0, 1.0])  # the ir_rig scene's cameras as a rig file made at twice their size
    write_rig(rig, Rig("bar", tuple(dataclasses.replace(camera, width=2 * camera.width, height=2 * camera.height,
                                                        K=doubled @ camera.K)
                                    for camera in make_scene("ir_rig").cameras)))
    images.mkdir()
    cv2.imwrite(str(images / "0.png"), np.zeros((480, 640), np.uint8))
    places = {"hd": hd, "rig": rig, "images": images, "recordings": RECORDINGS}
    job = procs.run("run", *[option.format(**places) for option in options])
    assert job.poll() == 2, job.describe()
    lines = [line for line in job.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and f" ERROR artrack: {expected.format(**places)}" in lines[0], job.stderr


def test_a_recording_is_replayed_on_the_rig_asked_for(procs, bus, tmp_path):
    """ARTRACK_RIG (the test's rig, in every process's environment) and --rig move a recording's replay off the
    rig it was made on, so two jobs of one recording run side by side, each on its own rig."""
    by_env, by_flag = tmp_path / "env.mcap", tmp_path / "flag.mcap"
    other = f"{bus.rig}-flag"
    jobs = [procs.artrack("run", "echo", "--source", f"recording:{RECORDINGS / 'pattern.mcap'}", "--record",
                          str(out), *options, name=out.stem)
            for out, options in ((by_env, ()), (by_flag, ("--rig", other)))]
    for job in jobs:
        assert job.wait(4 * START_S) == 0, job.describe()
    for out, rig in ((by_env, bus.rig), (by_flag, other)):
        info = summarise(out)
        assert info.metadata["artrack.recording"]["rig"] == rig
        keys = {channel.key for channel in info.channels if channel.messages}
        assert {f"ar/{rig}/cam0/image", f"ar/{rig}/cam0/truth", f"ar/{rig}/cam0/echo"} <= keys, keys
        assert all(key.startswith(f"ar/{rig}/") for key in keys), keys


@pytest.mark.parametrize("length", ["0", "-0.05"])
def test_run_refuses_a_marker_length_that_is_not_positive_naming_the_flag(procs, length):
    job = procs.run("run", "marker", "--source", "synthetic:markers", "--frames", "5", "--marker-length", length)
    assert job.poll() == 2, job.describe()
    lines = [line for line in job.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and "--marker-length: Input should be greater than 0" in lines[0], job.stderr


def test_run_without_marker_length_takes_the_markers_scenes_own_and_says_so(procs, tmp_path):
    saved = tmp_path / "job.toml"
    job = procs.run("run", "marker", "--source", "synthetic:markers", "--scene-option", "marker_length=0.07",
                    "--frames", "5", "--save-pipeline", str(saved))
    assert job.poll() == 0, job.describe()
    assert "using --marker-length 0.07, as synthetic:markers renders it" in job.stderr
    assert tomllib.loads(saved.read_text())["nodes"]["marker-cam0"]["marker_length"] == 0.07
    given = procs.run("run", "marker", "--source", "synthetic:markers", "--marker-length", "0.05", "--frames", "5",
                      "--save-pipeline", str(saved), "--force")
    assert given.poll() == 0 and "using --marker-length" not in given.stderr, given.describe()
    assert tomllib.loads(saved.read_text())["nodes"]["marker-cam0"]["marker_length"] == 0.05


def test_run_without_marker_length_on_other_sources_is_refused_before_starting(procs, tmp_path):
    cv2.imwrite(str(tmp_path / "0.png"), np.zeros((48, 64), np.uint8))
    job = procs.run("run", "marker", "--source", f"images:{tmp_path}")
    assert job.poll() == 2, job.describe()
    lines = [line for line in job.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and "nodes.marker-cam0: no marker side length" in lines[0] and "--marker-length" in lines[0]
