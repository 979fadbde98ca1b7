"""`artrack target add|list|show|remove|check` as a user runs them: a round trip through a library folder, the
refusals in one line with exit 2, and the check's verdicts as exit codes."""

import cv2
import numpy as np
import pytest

from services.synthetic import make_scene

pytestmark = pytest.mark.integration


@pytest.fixture(scope="module")
def texture():
    return make_scene("planar_target").texture


@pytest.fixture
def poster(tmp_path, texture):
    path = tmp_path / "poster.png"
    cv2.imwrite(str(path), texture[:360, :480])
    return path


def one_line_error(proc, *fragments):
    """Exit 2 with one stderr line holding every fragment."""
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert proc.poll() == 2 and len(lines) == 1, proc.describe()
    assert all(fragment in lines[0] for fragment in fragments), lines[0]


def test_add_list_show_remove_round_trip(procs, tmp_path, poster):
    library = str(tmp_path / "targets")
    added = procs.run("target", "add", str(poster), "--width", "0.2", "--targets", library)
    assert added.poll() == 0, added.describe()
    assert added.stdout.startswith("poster: 480x360 px, 0.200 x 0.150 m, ") and library in added.stdout
    sift = procs.run("target", "add", str(poster), "--width", "0.1", "--name", "small", "--feature", "sift",
                     "--targets", library)
    assert sift.poll() == 0, sift.describe()
    listed = procs.run("target", "list", "--targets", library)
    assert listed.poll() == 0, listed.describe()
    lines = listed.stdout.splitlines()
    assert [line.split(":")[0] for line in lines] == ["poster", "small"]
    assert "0.200 x 0.150 m, 480x360 px" in lines[0] and "orb keypoints" in lines[0] and "sift" in lines[1]
    shown = procs.run("target", "show", "small", "--targets", library)
    assert shown.poll() == 0, shown.describe()
    fields = dict(line.split(": ", 1) for line in shown.stdout.splitlines())
    assert fields["size"] == "480x360 px, 0.100 x 0.075 m" and fields["descriptors"] == "SIFT, 128 floats, l2"
    count = fields["keypoints"].split()[0]
    assert fields["detector"] == "sift, at most 2000 keypoints per 640x480 pixels"
    assert fields["keypoints"] == f"{count} ({count} at 1/1)"  # SIFT's own scale space, no pyramid of the image
    assert fields["check"].split(":")[0] in ("good", "fair")
    orb = dict(line.split(": ", 1) for line in procs.run("target", "show", "poster", "--targets", library)
               .stdout.splitlines())
    assert orb["detector"] == "orb, at most 2000 keypoints per level" and " at 1/2" in orb["keypoints"]
    removed = procs.run("target", "remove", "poster", "--targets", library)
    assert removed.poll() == 0 and "poster: removed" in removed.stdout, removed.describe()
    assert [line.split(":")[0] for line in procs.run("target", "list", "--targets", library).stdout.splitlines()] \
        == ["small"]
    one_line_error(procs.run("target", "show", "poster", "--targets", library), "no target 'poster'", "small")
    empty = procs.run("target", "list", "--targets", str(tmp_path / "none"))
    assert empty.poll() == 0 and empty.stdout.startswith("no targets in"), empty.describe()


def test_refusals_are_one_line_with_exit_2(procs, tmp_path, poster):
    library = str(tmp_path / "targets")
    one_line_error(procs.run("target", "add", str(tmp_path / "missing.png"), "--width", "0.2", "--targets", library),
                   "missing.png: no such file")
    for width in ("0", "-0.5", "nan"):
        one_line_error(procs.run("target", "add", str(poster), "--width", width, "--targets", library),
                       "positive number of metres")
    assert procs.run("target", "add", str(poster), "--width", "0.2", "--targets", library).poll() == 0
    one_line_error(procs.run("target", "add", str(poster), "--width", "0.3", "--targets", library),
                   "target 'poster' already exists")
    one_line_error(procs.run("target", "add", str(poster), "--width", "0.3", "--name", "other", "--feature", "surf",
                             "--targets", library), "feature 'surf'")
    one_line_error(procs.run("target", "remove", "other", "--targets", library), "no target 'other'")


def test_check_verdicts_are_exit_codes(procs, tmp_path, texture):
    images = {"good": texture, "fair": np.full(texture.shape, 128, np.uint8),
              "poor": np.tile(texture[300:364, 300:380], (12, 13))[:texture.shape[0], :texture.shape[1]]}
    images["fair"][:250, :300] = texture[:250, :300]
    for verdict, status in (("good", 0), ("fair", 1), ("poor", 2)):
        path = tmp_path / f"{verdict}.png"
        cv2.imwrite(str(path), images[verdict])
        checked = procs.run("target", "check", str(path))
        assert checked.poll() == status and checked.stdout.startswith(f"{verdict}: "), checked.describe()
        assert (verdict == "good") == ("warning:" not in checked.stdout)
        added = procs.run("target", "add", str(path), "--width", "0.2", "--targets", str(tmp_path / "targets"))
        warned = [line for line in added.stderr.splitlines() if "WARNING" in line]
        assert added.poll() == 0 and added.stdout.startswith(f"{verdict}: "), added.describe()
        rating = checked.stdout.splitlines()[0]
        assert warned == ([] if verdict == "good" else [warned[0]]), added.stderr
        said = f"{path} rates {rating} (`artrack target check {path}` says why)"
        assert verdict == "good" or warned[0].endswith(said), warned
    one_line_error(procs.run("target", "check", str(tmp_path / "missing.png")), "missing.png: no such file")


@pytest.mark.parametrize(("name", "make", "why"), [
    ("empty.png", lambda path: path.write_bytes(b""), "not an image OpenCV can read"),
    ("tiny.png", lambda path: cv2.imwrite(str(path), np.random.default_rng(1).integers(0, 256, (20, 20), np.uint8)),
     "20x20 px; it needs at least 32 px"),
    ("flat.png", lambda path: cv2.imwrite(str(path), np.full((300, 400), 128, np.uint8)), "has no keypoints"),
])
def test_unusable_images_are_refused_naming_the_file(procs, tmp_path, name, make, why):
    image = tmp_path / name
    make(image)
    library = tmp_path / "targets"
    one_line_error(procs.run("target", "add", str(image), "--width", "0.2", "--targets", str(library)),
                   f"target image {image}: ", why)
    assert not library.exists() or not any(library.iterdir())
