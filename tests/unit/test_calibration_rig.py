"""Rig files: the ir_rig scene's cameras survive a round trip; a rig that cannot be used is refused in one line."""

from pathlib import Path

import numpy as np
import pytest
import yaml

from services.calibration.camera_info import CalibrationError
from services.calibration.rig import Rig, read_rig, write_rig
from services.synthetic import make_scene


@pytest.fixture(scope="module")
def rig() -> Rig:
    return Rig("bar", make_scene("ir_rig", camera_count=3).cameras)


def written(tmp_path: Path, rig: Rig) -> tuple[Path, dict]:
    path = tmp_path / "rig.yaml"
    write_rig(path, rig)
    return path, yaml.safe_load(path.read_text())


def test_round_trip_keeps_every_camera(tmp_path, rig):
    path, _ = written(tmp_path, rig)
    back = read_rig(path)
    assert back.name == "bar" and back.names == ("cam0", "cam1", "cam2")
    for a, b in zip(rig.cameras, back.cameras, strict=True):
        assert (a.width, a.height) == (b.width, b.height)
        np.testing.assert_allclose(b.K, a.K, rtol=0, atol=1e-12)
        np.testing.assert_allclose(b.dist, a.dist, rtol=0, atol=1e-15)
        np.testing.assert_allclose(b.T_rig_camera, a.T_rig_camera, rtol=0, atol=1e-15)
    assert back.camera("cam1").name == "cam1"
    with pytest.raises(KeyError, match="cam0, cam1, cam2"):
        back.camera("cam7")


def refusal(tmp_path: Path, document: dict) -> str:
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(document))
    with pytest.raises(CalibrationError) as caught:
        read_rig(path)
    message = str(caught.value)
    assert str(path) in message and "\n" not in message
    return message


def test_one_camera_is_refused(tmp_path, rig):
    _, document = written(tmp_path, rig)
    document["cameras"] = document["cameras"][:1]
    assert "at least 2 cameras" in refusal(tmp_path, document)


def test_camera_without_extrinsics_is_refused(tmp_path, rig):
    _, document = written(tmp_path, rig)
    del document["cameras"][1]["T_rig_camera"]
    assert "cameras[1] (cam1): missing T_rig_camera" in refusal(tmp_path, document)


@pytest.mark.parametrize(("change", "words"), [
    (lambda T: T[:3, :3] * 1.01, "orthonormal"),
    (lambda T: T[:3, :3] @ np.diag([1.0, 1.0, -1.0]), "det"),
])
def test_non_rigid_extrinsics_are_refused(tmp_path, rig, change, words):
    _, document = written(tmp_path, rig)
    T = np.array(document["cameras"][2]["T_rig_camera"]["data"]).reshape(4, 4)
    T[:3, :3] = change(T)
    document["cameras"][2]["T_rig_camera"]["data"] = [float(v) for v in T.ravel()]
    message = refusal(tmp_path, document)
    assert "cameras[2] (cam2)" in message and words in message


def test_duplicate_names_are_refused(tmp_path, rig):
    _, document = written(tmp_path, rig)
    document["cameras"][1]["camera_name"] = "cam0"
    assert "distinct" in refusal(tmp_path, document)


def test_rig_built_in_code_checks_its_cameras(rig):
    with pytest.raises(ValueError, match="at least 2 cameras"):
        Rig("one", rig.cameras[:1])
