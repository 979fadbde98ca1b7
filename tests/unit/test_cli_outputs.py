"""The one rule for a command's output files: kept unless --force, refused before the work when unwritable."""

from __future__ import annotations

import pytest

from services.cli.outputs import check_output_folder
from services.runtime.outputs import check_output


def test_an_existing_file_is_refused_unless_forced(tmp_path):
    out = tmp_path / "out.rrd"
    check_output(out, force=False)  # nothing there yet
    out.write_text("kept")
    with pytest.raises(ValueError, match=f"^{out} exists: give --force to overwrite it$"):
        check_output(out, force=False)
    check_output(out, force=True)
    assert out.read_text() == "kept"  # checking writes nothing


def test_a_missing_folder_is_refused_unless_the_command_makes_it(tmp_path):
    out = tmp_path / "a" / "b" / "cam.yaml"
    with pytest.raises(ValueError, match=f"^cannot write {out}: folder {out.parent} does not exist$"):
        check_output(out, force=True)
    check_output(out, force=False, makes_folders=True)
    assert not (tmp_path / "a").exists()


def test_a_folder_or_a_file_in_place_of_a_folder_is_refused(tmp_path):
    with pytest.raises(ValueError, match="is a folder: give a file name"):
        check_output(tmp_path, force=True)
    blocker = tmp_path / "file"
    blocker.write_text("")
    with pytest.raises(ValueError, match=f"^cannot write {blocker / 'y'}: {blocker} is not a folder$"):
        check_output(blocker / "y", force=False)
    with pytest.raises(ValueError, match=f"^cannot write {blocker / 'x' / 'y'}: {blocker} is not a folder$"):
        check_output(blocker / "x" / "y", force=False, makes_folders=True)


def test_an_output_folder_is_kept_unless_forced_and_only_one_of_ours_is_ever_replaced(tmp_path):
    out = tmp_path / "bag"
    check_output_folder(out, force=False, marker="metadata.yaml")  # nothing there yet
    out.mkdir()
    with pytest.raises(ValueError, match=f"^{out} exists: give --force to overwrite it$"):
        check_output_folder(out, force=False, marker="metadata.yaml")
    check_output_folder(out, force=True, marker="metadata.yaml")  # empty: nothing to lose
    (out / "notes.txt").write_text("mine")
    with pytest.raises(ValueError, match=f"^{out} exists and has no metadata.yaml: not overwriting"):
        check_output_folder(out, force=True, marker="metadata.yaml")
    (out / "metadata.yaml").write_text("")
    check_output_folder(out, force=True, marker="metadata.yaml")
    with pytest.raises(ValueError, match=f"^{out / 'notes.txt'} is a file: give a folder name$"):
        check_output_folder(out / "notes.txt", force=True, marker="metadata.yaml")
    with pytest.raises(ValueError, match=f"^cannot write {tmp_path / 'a' / 'b'}: folder {tmp_path / 'a'} does not"):
        check_output_folder(tmp_path / "a" / "b", force=False, marker="metadata.yaml")
