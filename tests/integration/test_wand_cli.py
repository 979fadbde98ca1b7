"""``artrack calibrate --wand``: a recording of the ``ir_rig`` scene's wand, rendered images and camera_info,
gives the rig's extrinsics (blobs found by the IR blob detector), scored against the scene's truth."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from protocol import Header, encode
from protocol.sensors import Image
from services.calibration.camera_info import camera_document
from services.calibration.rig import read_rig
from services.convert import camera_info
from services.geometry.rotation import rotation_angle
from services.geometry.se3 import invert
from services.recorder.writing import RecordingWriter
from services.synthetic import make_scene
from services.synthetic.ir_rig import LFRAME_BODY
from tests.wand_blobs import extrinsic_errors

pytestmark = pytest.mark.integration

PREFIX = "ar/lab"
FRAMES = range(0, 1000, 5)


def artrack(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "services.cli", *args], capture_output=True, text=True, timeout=300)


def record(path: Path, camera_count: int, frames: range = FRAMES, with_info: bool = True, motion: str = "wand"):
    """Write the ``motion`` scene's images (and camera_info) to ``path``; return the scene."""
    scene = make_scene("ir_rig", motion=motion, camera_count=camera_count, noise_std=1.0)
    writer = RecordingWriter(path, metadata={"namespace": "ar", "rig": "lab"})
    for seq, index in enumerate(frames):
        frame = scene.render(index)
        stamp = 1_700_000_000_000_000_000 + index * 33_333_333
        for camera in scene.cameras:
            header = Header(stamp_ns=stamp, frame_id=camera.name, seq=seq)
            image = Image(header=header, encoding="mono8", data=frame.images[camera.name])
            writer.write(f"{PREFIX}/{camera.name}/image", encode(image), stamp)
            if with_info:
                writer.write(f"{PREFIX}/{camera.name}/camera_info", encode(camera_info(header, camera)), stamp + 1)
    writer.close()
    return scene


@pytest.fixture(scope="module")
def three_cameras(tmp_path_factory) -> tuple[Path, object]:
    """The three-camera wand recording (read only) and its scene, made once for the tests that calibrate it."""
    recording = tmp_path_factory.mktemp("wand") / "wand.mcap"
    return recording, record(recording, 3)


def test_wand_recording_gives_the_rig_extrinsics(tmp_path, three_cameras):
    recording, scene = three_cameras
    out = tmp_path / "rig.yaml"
    done = artrack("calibrate", "--wand", str(recording), "--wand-length", "0.5", "--wand-middle", "0.15",
                   "-o", str(out))
    assert done.returncode == 0, done.stderr
    print(done.stdout)
    assert "reprojection RMS" in done.stdout and f"wrote {out}" in done.stdout
    rig = read_rig(out)
    assert rig.names == ("cam0", "cam1", "cam2")
    estimate = [rig.camera(camera.name).T_rig_camera for camera in scene.cameras]
    position_mm, rotation_deg = extrinsic_errors(scene, estimate)
    assert position_mm.max() < 1.0 and rotation_deg.max() < 0.05
    for camera in scene.cameras:
        assert np.array_equal(rig.camera(camera.name).K, camera.K)


def test_floor_frame_from_a_recorded_lframe(tmp_path, three_cameras):
    recording, _ = three_cameras
    floor, out = tmp_path / "lframe.mcap", tmp_path / "rig.yaml"
    scene = record(floor, 3, frames=range(10), motion="lframe")
    done = artrack("calibrate", "--wand", str(recording), "--wand-length", "0.5", "--wand-middle", "0.15",
                   "--floor", str(floor), "-o", str(out))
    assert done.returncode == 0, done.stderr
    assert "floor frame from 10 of 10 frames" in done.stdout
    rig = read_rig(out)
    T_floor_world = invert(scene.body_poses(0)[LFRAME_BODY])
    for camera in scene.cameras:
        truth, estimate = T_floor_world @ camera.T_rig_camera, rig.camera(camera.name).T_rig_camera
        assert np.linalg.norm(truth[:3, 3] - estimate[:3, 3]) < 2e-3
        assert np.degrees(rotation_angle(truth[:3, :3], estimate[:3, :3])) < 0.1


def test_intrinsics_from_files_and_their_order(tmp_path):
    recording, out = tmp_path / "wand.mcap", tmp_path / "rig.yaml"
    scene = record(recording, 2, with_info=False)
    files = []
    for camera in reversed(scene.cameras):
        files.append(tmp_path / f"{camera.name}.yaml")
        files[-1].write_text(yaml.safe_dump(camera_document(camera)))
    done = artrack("calibrate", "--wand", str(recording), "--wand-length", "0.5", "--wand-middle", "0.35",
                   "--intrinsics", *map(str, files), "-o", str(out))
    assert done.returncode == 0, done.stderr
    rig = read_rig(out)
    assert rig.names == ("cam1", "cam0")
    assert np.allclose(rig.camera("cam1").T_rig_camera, np.eye(4))
    T_cam1_cam0 = invert(scene.cameras[1].T_rig_camera) @ scene.cameras[0].T_rig_camera
    assert np.linalg.norm(rig.camera("cam0").T_rig_camera[:3, 3] - T_cam1_cam0[:3, 3]) < 1e-3


@pytest.fixture(scope="module")
def short_two_cameras(tmp_path_factory) -> Path:
    """A four-frame wand recording of two cameras without camera_info (read only)."""
    recording = tmp_path_factory.mktemp("short") / "wand.mcap"
    record(recording, 2, frames=range(0, 20, 5), with_info=False)
    return recording


BAD_INPUT = {
    "no wand length": (["--wand", "{recording}"], "--wand needs --wand-length"),
    "middle marker at the centre": (["--wand", "{recording}", "--wand-length", "0.5", "--wand-middle", "0.25"],
                                    "off the wand's centre"),
    "no intrinsics": (["--wand", "{recording}", "--wand-length", "0.5", "--wand-middle", "0.15"],
                      "no intrinsics for camera 'cam0'"),
    "missing recording": (["--wand", "{tmp}/none.mcap", "--wand-length", "0.5", "--wand-middle", "0.15"],
                          "none.mcap"),
    "no input": ([], "calibrate needs DIR_OR_GLOB, --pattern, --size, --square"),
    "missing intrinsics file": (["--wand", "{recording}", "--wand-length", "0.5", "--wand-middle", "0.15", "--floor",
                                 "{recording}", "--intrinsics", "{tmp}/none.yaml"], "none.yaml"),
}
"""Case -> (``artrack calibrate`` arguments before ``-o``, with ``{recording}`` and ``{tmp}`` filled in; what the
one line of stderr says)."""


@pytest.mark.parametrize("case", list(BAD_INPUT))
def test_bad_wand_input_is_one_clear_line(tmp_path, short_two_cameras, case):
    template, message = BAD_INPUT[case]
    out = str(tmp_path / "rig.yaml")
    args = [arg.format(recording=short_two_cameras, tmp=tmp_path) for arg in template]
    done = artrack("calibrate", *args, "-o", out)
    assert done.returncode == 2, (args, done.stdout)
    assert message in done.stderr and "Traceback" not in done.stderr, done.stderr
    assert len(done.stderr.strip().splitlines()) == 1, done.stderr
    assert not Path(out).exists()
