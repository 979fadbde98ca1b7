"""Process groups: which nodes share a process, the commands that start them, and the local deliveries' registry."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from protocol.flow import FlowAck
from protocol.message import Header
from services.bus.local import LocalBus, deliver
from services.bus.session import BusConfig
from services.launcher.health import pipeline_health
from services.launcher.job import build_job
from services.launcher.layout import SINGLE, laid_out
from services.launcher.pipeline import (
    GROUP_MEMBERS,
    NodeSpec,
    PipelineError,
    PipelineSpec,
    processes,
    read_pipeline,
    resolved,
    to_toml,
)
from services.launcher.supervisor import ChildHealth
from services.launcher.tracker import Tracker
from services.runtime.group import worst
from services.runtime.restarts import EXIT_CANNOT_RUN


class Sink:
    def __init__(self, key: str, wants_bytes: bool = False):
        self.key = key
        self.wants_bytes = wants_bytes
        self.got: list[tuple[str, object]] = []

    def offer(self, key: str, payload: object) -> None:
        self.got.append((key, payload))


def test_the_local_bus_finds_subscribers_by_key_expression_and_forgets_those_gone():
    local = LocalBus()
    exact, every, other = Sink("ar/r/cam0/image"), Sink("ar/r/*/image"), Sink("ar/r/cam1/**")
    for sink in (exact, every, other):
        local.attach(sink)
    assert local.sinks("ar/r/cam0/image") == (exact, every)
    assert local.sinks("ar/r/cam1/image") == (every, other)
    local.detach(every)
    assert local.sinks("ar/r/cam0/image") == (exact,)


def test_a_message_reaches_local_subscribers_as_itself_and_raw_taps_encoded_once():
    message = FlowAck(header=Header(stamp_ns=1), node="n", seq=3, started_ns=2)
    typed, raw, raw_too = Sink("k"), Sink("k", wants_bytes=True), Sink("k", wants_bytes=True)
    encodings: list[int] = []

    def encoded() -> bytes:
        encodings.append(1)
        return b"encoded"

    deliver((typed, raw, raw_too), "k", message, encoded)
    assert typed.got[0][1] is message
    assert raw.got == raw_too.got == [("k", b"encoded")]
    assert len(encodings) == 2  # the publisher caches it; ``deliver`` asks per tap


def _spec(**processes_of: str | None) -> PipelineSpec:
    nodes = {"cam": NodeSpec(kind="capture", source="synthetic:pattern", cameras=["cam0"], frames=5,
                             process=processes_of.get("cam")),
             "echo": NodeSpec(kind="echo", camera="cam0", process=processes_of.get("echo")),
             "rec": NodeSpec(kind="recorder", out="/tmp/never-written.mcap", process=processes_of.get("rec"))}
    return resolved(PipelineSpec(nodes=nodes))


def test_nodes_naming_one_process_are_one_group_and_the_others_alone():
    spec = _spec(cam="camera", echo="camera")
    assert spec.groups() == {"camera": ("cam", "echo"), "rec": ("rec",)}
    assert [spec.process_of(name) for name in spec.nodes] == ["camera", "camera", "rec"]


def test_a_group_named_after_a_node_of_another_process_is_refused():
    with pytest.raises(ValueError, match=r"nodes.echo.process: 'rec' is the name of a node in another process"):
        _spec(echo="rec", rec="elsewhere")


def test_a_group_starts_as_one_command_that_carries_each_nodes_params_flow_and_role():
    spec = _spec(cam="camera", echo="camera")
    started = {p.name: p for p in processes(spec, BusConfig(rig="r", autostart_router=False))}
    assert set(started) == {"camera", "rec"}
    assert started["rec"].argv[3:5] == ("node", "recorder")
    argv = started["camera"].argv
    assert argv[3:5] == ("group", "camera")
    members = GROUP_MEMBERS.validate_json(argv[argv.index("--nodes") + 1])
    assert [(m.name, m.kind, m.source) for m in members] == [("cam", "capture", True), ("echo", "echo", False)]
    assert members[0].params["frames"] == 5 and members[1].flow.upstream == ("cam",)


def test_a_process_restarts_only_when_every_node_in_it_may():
    spec = _spec(cam="camera", echo="camera")
    spec = spec.model_copy(update={"nodes": {**spec.nodes, "echo": spec.nodes["echo"].model_copy(
        update={"restart": False})}})
    assert {p.name: p.restart for p in processes(spec, BusConfig(rig="r", autostart_router=False))} == {
        "camera": False, "rec": True}


def test_a_pipeline_file_keeps_its_groups_through_writing_and_reading(tmp_path: Path):
    path = tmp_path / "p.toml"
    path.write_text(to_toml(_spec(cam="camera", echo="camera")))
    assert read_pipeline(path).groups() == {"camera": ("cam", "echo"), "rec": ("rec",)}


def test_layouts_split_or_join_the_nodes_and_moves_place_one():
    spec = _spec(cam="camera", echo="camera")
    assert laid_out(spec, "separate").groups() == {"cam": ("cam",), "echo": ("echo",), "rec": ("rec",)}
    assert laid_out(spec, "single").groups() == {SINGLE: ("cam", "echo"), "rec": ("rec",)}
    assert laid_out(spec, "given", ["echo="]).groups() == {"camera": ("cam",), "echo": ("echo",), "rec": ("rec",)}
    assert laid_out(spec, "separate", ["rec=cam"]).groups() == {"cam": ("cam", "rec"), "echo": ("echo",)}
    with pytest.raises(PipelineError, match=r"--process 'blobs=x': give NODE=PROCESS .* one of cam, echo, rec"):
        laid_out(spec, "given", ["blobs=x"])


def test_the_stereo_template_runs_the_source_and_blobs_in_one_process_and_the_bodies_apart():
    tracker = Tracker.load("stereo")
    source = NodeSpec(kind="capture", source="synthetic:ir_rig", frames=3)
    spec = build_job(tracker, source, {}, tracker.flags({}))
    assert spec.groups() == {"rig": ("capture", "blobs-cam0", "blobs-cam1"), "bodies": ("bodies",)}
    assert tracker.layout() == "process rig: the source, blobs-{camera}; bodies alone"


def test_the_nodes_of_a_group_answer_status_with_their_process_health():
    spec = _spec(cam="camera", echo="camera")
    children = [ChildHealth("camera", "running", 41, 2.0, 1, None), ChildHealth("rec", "running", 42, 2.0, 0, None)]
    health = pipeline_health("p", spec, children, 3.0)
    assert [(n.name, n.kind, n.pid, n.restarts) for n in health.nodes] == [
        ("cam", "capture", 41, 1), ("echo", "echo", 41, 1), ("rec", "recorder", 42, 0)]


@pytest.mark.parametrize(("codes", "expected"), [((0, 0), 0), ((0, 3), 3), ((3, 1), 1), ((1, EXIT_CANNOT_RUN), 2),
                                                 ((), 0)])
def test_a_group_exits_with_its_worst_members_code(codes, expected):
    assert worst(list(codes)) == expected


def test_group_members_refuse_unknown_fields():
    with pytest.raises(ValueError, match="extra"):
        GROUP_MEMBERS.validate_json(json.dumps([{"name": "a", "kind": "echo", "colour": 1}]))
