"""Names of a recording's files: split parts, and the continuations a restarted recorder writes."""

from __future__ import annotations

from pathlib import Path

import pytest

from services.recorder.writing import check_target, recording_parts, restart_target


def _touch(folder: Path, *names: str) -> None:
    for name in names:
        (folder / name).write_bytes(b"")


def test_a_restarted_recorder_goes_on_in_the_next_free_continuation(tmp_path):
    out = tmp_path / "run.mcap"
    assert restart_target(out) == out  # nothing begun: the file itself
    _touch(tmp_path, "run.mcap")
    assert restart_target(out) == tmp_path / "run.part2.mcap"
    _touch(tmp_path, "run.part2.mcap")
    assert restart_target(out) == tmp_path / "run.part3.mcap"


def test_the_parts_of_a_recording_are_in_order_and_others_are_not_among_them(tmp_path):
    _touch(tmp_path, "run_000.mcap", "run_001.mcap", "run.part2_000.mcap", "run.part10.mcap", "run.part3.mcap",
           "run.partial.mcap", "run.part1.mcap", "running.mcap", "run.part3.txt")
    names = [p.name for p in recording_parts(tmp_path / "run.mcap")]
    assert names == ["run_000.mcap", "run_001.mcap", "run.part2_000.mcap", "run.part3.mcap", "run.part10.mcap"]
    assert restart_target(tmp_path / "run.mcap") == tmp_path / "run.part11.mcap"


@pytest.mark.parametrize("existing", ["run.mcap", "run_000.mcap", "run.part2.mcap", "run.part4_001.mcap"])
def test_a_fresh_recording_refuses_any_file_of_an_earlier_one(tmp_path, existing):
    _touch(tmp_path, existing)
    with pytest.raises(ValueError, match=f"{existing} exists"):
        check_target(tmp_path / "run.mcap")
