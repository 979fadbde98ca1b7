"""What the recorder subscribes to, what replay selects and with which QoS, where recordings may go."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta, timezone

import pytest
from mcap.records import Channel

from protocol.keys import Keys
from services.bus.pubsub import Role
from services.recorder.record_node import Params as RecordParams
from services.recorder.record_node import subscriptions
from services.recorder.replay_node import Params as ReplayParams
from services.recorder.replay_node import Selection, role_of
from services.recorder.writing import check_target, part_path

KEYS = Keys("ar", "lab")


def channel(topic: str, number: int = 1) -> Channel:
    return Channel(id=number, topic=topic, message_encoding="json", metadata={}, schema_id=1)


def test_subscriptions_cover_the_rig_by_default_and_never_twice():
    assert subscriptions(KEYS, ()) == ["ar/lab/**"]
    assert subscriptions(KEYS, ("pose/**", "ar/lab/pose/a", "cam0/image")) == ["ar/lab/pose/**", "ar/lab/cam0/image"]
    assert subscriptions(KEYS, ("cam0/image", "**")) == ["ar/lab/**"]
    assert subscriptions(KEYS, ("ar/other/**",)) == ["ar/other/**"]  # absolute when it starts with the namespace
    with pytest.raises(ValueError, match="overlap: a message on both would be recorded twice"):
        subscriptions(KEYS, ("*/image", "cam0/*"))


def test_replay_leaves_out_node_health_unless_asked_for_it():
    default = Selection(KEYS, ())
    assert default(channel("ar/lab/cam0/image")) and default(channel("other/ns/key", 2))
    assert not default(channel("ar/lab/node/recorder/stats", 3)) and not default(channel("ar/x/node/y/errors", 4))
    chosen = Selection(KEYS, ("pose/**", "node/**"))
    assert chosen(channel("ar/lab/pose/a")) and chosen(channel("ar/lab/node/cam/stats", 2))
    assert not chosen(channel("ar/lab/cam0/image", 3))
    assert [str(k) for k in chosen.probes] == ["ar/lab/pose/**", "ar/lab/node/**"]


def test_roles_follow_the_schema():
    assert role_of("artrack.Image") is Role.FRAME
    assert role_of("artrack.NodeStats") is Role.STATUS and role_of("artrack.ErrorReport") is Role.STATUS
    assert role_of("artrack.Pose") is Role.RESULT and role_of(None) is Role.RESULT  # raw payloads are never dropped


def test_recordings_are_never_overwritten(tmp_path):
    out = tmp_path / "run.mcap"
    check_target(out)
    part_path(out, 4).write_bytes(b"")
    with pytest.raises(ValueError, match="run_004.mcap exists"):
        check_target(out)
    with pytest.raises(ValueError, match="does not exist"):
        check_target(tmp_path / "missing" / "run.mcap")


def test_a_start_placeholder_gives_each_start_its_own_file(tmp_path):
    params = RecordParams(out=tmp_path / "rig-{start}.mcap", split_duration_s=600)
    first = params.target(datetime(2026, 11, 24, 5, 10, 0, tzinfo=UTC))
    assert first == tmp_path / "rig-20261124T051000Z.mcap"
    part_path(first, 0).write_bytes(b"")
    with pytest.raises(ValueError, match="exists"):
        check_target(first)
    check_target(params.target(datetime(2026, 11, 24, 6, 10, 1, tzinfo=timezone(timedelta(hours=1)))))
    assert RecordParams(out=tmp_path / "run.mcap").target(datetime.now(UTC)) == tmp_path / "run.mcap"


def test_parameters_refuse_contradictions():
    with pytest.raises(ValueError, match="split by size or by duration, not both"):
        RecordParams(out="x.mcap", split_size_mb=10, split_duration_s=5)
    assert RecordParams(out="x.mcap", split_duration_s=2.5).split().duration_ns == 2_500_000_000
    with pytest.raises(ValueError, match="must be after start_s"):
        ReplayParams(path="x.mcap", start_s=5, end_s=2)
    assert ReplayParams(path="x.mcap", start_s=1, end_s=2).window().end_ns == 2_000_000_000
