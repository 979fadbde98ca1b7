"""Where each bus field comes from: a flag, else its environment variable, else a pipeline file, else its default."""

from __future__ import annotations

from pathlib import Path

import pytest

from protocol.keys import Keys
from services.bus.session import BusConfig
from services.recorder.replay_node import Retarget, recorded_prefix
from services.recorder.writing import RecordingWriter

ROOT = Path(__file__).resolve().parents[2]
FILE = {"rig": "filerig", "namespace": "site/lab1", "autostart_router": False}


@pytest.mark.parametrize(
    ("environ", "flags", "expected"),
    [
        ({}, {}, ("filerig", "site/lab1")),
        ({"ARTRACK_RIG": "envrig"}, {}, ("envrig", "site/lab1")),
        ({"ARTRACK_RIG": "envrig"}, {"rig": "flagrig"}, ("flagrig", "site/lab1")),
        ({"ARTRACK_NAMESPACE": "envns"}, {"rig": "flagrig", "namespace": None}, ("flagrig", "envns")),
    ],
)
def test_flag_beats_environment_beats_file(environ: dict, flags: dict, expected: tuple):
    bus = BusConfig.from_env(environ, defaults=FILE, **flags)
    assert (bus.rig, bus.namespace) == expected


def test_without_file_or_environment_the_defaults_hold():
    assert (BusConfig.from_env({}, defaults={}).rig, BusConfig.from_env({}).namespace) == ("rig0", "ar")


def test_a_file_security_table_is_completed_field_by_field_by_the_environment():
    file = {"mode": "client", "connect": ["tcp/h:1"], "security": {"user": "fileuser"}}
    bus = BusConfig.from_env({"ARTRACK_PASSWORD": "secret"}, defaults=file)
    assert bus.security.user == "fileuser" and bus.security.password is not None


def test_overridden_names_the_variables_that_beat_a_file_value_and_only_those():
    environ = {"ARTRACK_RIG": "envrig", "ARTRACK_NAMESPACE": "envns", "ARTRACK_ROUTER_AUTOSTART": "0",
               "ARTRACK_MODE": "client", "ARTRACK_CONNECT": "tcp/h:1"}
    flags = {"namespace": "flagns"}
    bus = BusConfig.from_env(environ, defaults=FILE, **flags)
    # rig: the environment wins over the file; namespace: the flag wins; autostart: the same value as the file's;
    # mode: the file does not set it.
    assert bus.overridden(FILE, environ, **flags) == {"ARTRACK_RIG": "rig"}


def test_retarget_moves_the_recorded_rig_keys_and_keeps_the_others():
    move = Retarget("ar/rig0", Keys("ns2", "nc2"))
    assert move("ar/rig0/cam0/image") == "ns2/nc2/cam0/image"
    assert move("ar/rig0/pose/cam0/marker/3") == "ns2/nc2/pose/cam0/marker/3"
    assert move("ar/rig01/cam0/image") == "ar/rig01/cam0/image"
    assert move("other/rig0/cam0/image") == "other/rig0/cam0/image"


def test_recorded_prefix_reads_the_recording_metadata(tmp_path):
    assert recorded_prefix(ROOT / "recordings" / "markers.mcap") == "ar/rig0"
    bare = tmp_path / "bare.mcap"
    writer = RecordingWriter(bare)
    writer.write("x/y", b"\x00", 1)
    writer.close()
    with pytest.raises(ValueError, match="bare.mcap: no artrack.recording metadata"):
        recorded_prefix(bare)
