"""The target library: add, list, load and remove round trips, the default folder, and one-line refusals."""

import json
import zipfile

import cv2
import numpy as np
import pytest

from services.estimation.targets.features import feature_params
from services.estimation.targets.library import (
    DamagedTargetError,
    DuplicateTargetError,
    TargetImageError,
    TargetLibrary,
    TargetLibraryError,
    UnknownTargetError,
    default_library_dir,
)
from services.synthetic import make_scene


@pytest.fixture(scope="module")
def image_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("images") / "poster.png"
    cv2.imwrite(str(path), make_scene("planar_target").texture[:360, :480])
    return path


@pytest.fixture
def library(tmp_path):
    return TargetLibrary(tmp_path / "targets")


def test_add_list_load_remove_round_trip(library, image_file):
    assert library.names() == [] and library.list() == []
    added = library.add(image_file, 0.2)
    library.add(image_file, 0.1, name="small", feature="sift")
    assert library.names() == ["poster", "small"]
    infos = library.list()
    assert [(i.name, i.feature, i.image_size) for i in infos] == [("poster", "orb", (480, 360)),
                                                                  ("small", "sift", (480, 360))]
    assert infos[0].width_m == 0.2 and infos[0].height_m == pytest.approx(0.15)
    assert infos[0].keypoints == len(added.keypoints) and infos[0].source == str(image_file.resolve())
    loaded = library.load("poster")
    assert loaded.name == "poster" and loaded.width_m == 0.2 and loaded.feature == "orb"
    for field in ("image", "keypoints", "levels", "descriptors", "points"):
        assert getattr(loaded, field).dtype == getattr(added, field).dtype
        np.testing.assert_array_equal(getattr(loaded, field), getattr(added, field))
    assert library.load("small").descriptors.dtype == np.float32
    library.remove("poster")
    assert library.names() == ["small"]
    assert sorted(p.name for p in library.folder.iterdir()) == ["small.npz", "small.png"]
    with pytest.raises(UnknownTargetError, match=r"no target 'poster' in .* \(targets: small\)"):
        library.load("poster")
    with pytest.raises(UnknownTargetError):
        library.remove("poster")


def test_the_default_folder_follows_xdg(monkeypatch, tmp_path):
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path))
    assert default_library_dir() == tmp_path / "artrack" / "targets"
    assert TargetLibrary().folder == tmp_path / "artrack" / "targets"
    monkeypatch.delenv("XDG_DATA_HOME")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert default_library_dir() == tmp_path / "home" / ".local" / "share" / "artrack" / "targets"


def test_refusals_are_one_line_value_errors(library, image_file, tmp_path):
    with pytest.raises(TargetImageError, match="no such file"):
        library.add(tmp_path / "missing.png", 0.2)
    (tmp_path / "text.png").write_text("not an image")
    with pytest.raises(TargetImageError, match="not an image OpenCV can read"):
        library.add(tmp_path / "text.png", 0.2)
    flat = tmp_path / "flat.png"
    cv2.imwrite(str(flat), np.full((300, 300), 90, np.uint8))
    with pytest.raises(TargetImageError, match="no keypoints"):
        library.add(flat, 0.2)
    for width in (0, -0.3, float("nan")):
        with pytest.raises(TargetLibraryError, match="positive number of metres"):
            library.add(image_file, width)
    with pytest.raises(TargetLibraryError, match="target name"):
        library.add(image_file, 0.2, name="../escape")
    library.add(image_file, 0.2)
    with pytest.raises(DuplicateTargetError, match="already exists"):
        library.add(image_file, 0.3)
    assert library.add(image_file, 0.3, replace=True).width_m == 0.3
    for refused in (TargetImageError, TargetLibraryError, DuplicateTargetError, UnknownTargetError,
                    DamagedTargetError):
        assert issubclass(refused, ValueError)
    assert library.names() == ["poster"]


def rewrite(path, **changes):
    """Rewrite the target file at ``path`` with arrays replaced (None drops one) or header keys changed."""
    with np.load(path) as archive:
        arrays = {key: archive[key] for key in archive.files}
    header = json.loads(arrays["header"].tobytes())
    header.update(changes.pop("header", {}))
    arrays["header"] = np.frombuffer(json.dumps(header).encode(), np.uint8)
    arrays.update(changes)
    np.savez(path, **{key: value for key, value in arrays.items() if value is not None})


@pytest.mark.parametrize(("damage", "reason"), [
    (lambda p: p.write_bytes(p.read_bytes()[:200]), "unreadable"),
    (lambda p: p.write_text("plain text"), "unreadable"),
    (lambda p: rewrite(p, header={"version": 7}), "format version 7"),
    (lambda p: rewrite(p, header={"version": 1}), "format version 1, this version reads 2: add the target again"),
    (lambda p: rewrite(p, header={"detector": None}), "no detector settings"),
    (lambda p: rewrite(p, header={"detector": {"method": "surf"}}), "method: Input should be 'orb', 'sift'"),
    (lambda p: rewrite(p, header={"detector": {"method": "orb", "pattern": 3}}), "pattern: Extra inputs"),
    (lambda p: rewrite(p, header={"detector": {"method": "sift"}}), r"not \(N, 128\) float32"),
    (lambda p: rewrite(p, header={"format": "other"}), "not an artrack-target file"),
    (lambda p: rewrite(p, header={"width_m": -1}), "width_m -1"),
    (lambda p: rewrite(p, header={"image": "../x.png"}), "not a file beside it"),
    (lambda p: rewrite(p, header={"image_size": [10, 10]}), "the header says 10x10"),
    (lambda p: rewrite(p, descriptors=None), "descriptors missing"),
    (lambda p: rewrite(p, points=np.zeros((3, 3))), "points missing or not"),
    (lambda p: rewrite(p, points=np.load(p)["points"] * 2), "points do not lie"),
    (lambda p: p.with_suffix(".png").unlink(), "poster.png is missing"),
])
def test_a_damaged_file_is_named_with_its_fault(library, image_file, damage, reason):
    library.add(image_file, 0.2)
    path = library.folder / "poster.npz"
    damage(path)
    with pytest.raises(DamagedTargetError, match=reason) as error:
        library.load("poster")
    assert str(path) in str(error.value) and "\n" not in str(error.value)
    with pytest.raises(DamagedTargetError):
        library.list()


def test_a_file_is_a_zip_of_plain_arrays(library, image_file):
    library.add(image_file, 0.2)
    with zipfile.ZipFile(library.folder / "poster.npz") as archive:
        assert sorted(archive.namelist()) == ["descriptors.npy", "header.npy", "keypoints.npy", "levels.npy",
                                              "points.npy"]
    with np.load(library.folder / "poster.npz", allow_pickle=False) as archive:
        header = json.loads(archive["header"].tobytes())
    assert header["format"] == "artrack-target" and header["version"] == 2 and header["image"] == "poster.png"
    assert header["detector"] == feature_params("orb").model_dump()


def test_a_target_keeps_its_detector_settings_and_counts_per_level(library, image_file):
    settings = feature_params("orb").model_copy(update={"max_count": 300, "fast_threshold": 9})
    added = library.add(image_file, 0.2, feature=settings)
    loaded = library.load("poster")
    assert added.detector == loaded.detector == settings
    info = library.info("poster")
    assert info.detector == settings and info.descriptor == "ORB, 32 bytes, hamming"
    assert sum(info.per_level) == info.keypoints and len(info.per_level) == 2 and max(info.per_level) <= 300
    assert library.info("poster") == info
