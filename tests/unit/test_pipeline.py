"""Pipeline files and bus settings: what validates, and errors that name the field."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from services.bus.session import BusConfig
from services.launcher.pipeline import PipelineError, processes, read_pipeline

REPO = Path(__file__).resolve().parents[2]

PIPELINE = """
[bus]
rig = "demo"
namespace = "site/lab1"

[nodes.cam]
kind = "capture"
cameras = ["left"]
fps = 15
restart = false

[nodes.relay]
kind = "echo"
camera = "left"
"""


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "pipeline.toml"
    path.write_text(text)
    return path


def pipeline_error(path: Path) -> str:
    with pytest.raises(PipelineError) as caught:
        read_pipeline(path)
    message = str(caught.value)
    assert message.startswith(f"{path}: ")
    return message


def test_pipeline_is_read_with_bus_nodes_and_params(tmp_path):
    spec = read_pipeline(write(tmp_path, PIPELINE))
    assert spec.bus == {"rig": "demo", "namespace": "site/lab1"}
    assert list(spec.nodes) == ["cam", "relay"]
    cam, relay = spec.nodes["cam"], spec.nodes["relay"]
    assert (cam.kind, cam.restart, cam.params) == ("capture", False, {"cameras": ["left"], "fps": 15})
    assert (relay.kind, relay.restart, relay.params) == ("echo", True, {"camera": "left"})


def test_processes_run_each_node_with_its_params_and_the_bus(tmp_path):
    spec = read_pipeline(write(tmp_path, PIPELINE))
    bus = BusConfig.from_env({}, **spec.bus)
    cam, relay = processes(spec, bus)
    assert (cam.name, cam.restart, relay.name, relay.restart) == ("cam", False, "relay", True)
    assert cam.argv[:3] == (sys.executable, "-m", "services.cli")
    params = json.dumps({"cameras": ["left"], "fps": 15})
    assert cam.argv[3:9] == ("node", "capture", "--name", "cam", "--params", params)
    assert cam.argv[9] == "--flow" and json.loads(cam.argv[10]) == {}  # an endless source: real-time, no credits
    assert relay.argv[-2:] == ("--flow", json.dumps({"upstream": ["cam"]}, separators=(",", ":")))
    assert BusConfig.from_env(cam.env) == bus
    assert bus.keys.image("left") == "site/lab1/demo/left/image"


SHIPPED = {
    "echo.toml": {"cam": "capture", "echo": "echo"},
    "marker.toml": {"capture": "capture", "marker-cam0": "marker_pose"},
    "marker_board.toml": {"cam": "capture", "markers": "markers", "pose": "marker_pose"},
}
"""Each pipeline file shipped in pipelines/: its nodes' names and kinds."""


def test_shipped_pipelines_validate_as_the_nodes_they_hold():
    kinds = {path.name: {name: node.kind for name, node in read_pipeline(path).nodes.items()}
             for path in sorted((REPO / "pipelines").glob("*.toml"))}
    assert kinds == SHIPPED


NODES = '[nodes.cam]\nkind = "capture"\n'
FAULTS = [
    ("", "nodes: Field required"),
    ("[nodes]\n", "nodes: Dictionary should have at least 1 item"),
    (NODES + "[extra]\nx = 1\n", "extra: Extra inputs are not permitted"),
    ("[nodes.cam]\nfps = 3\n", "nodes.cam.kind: Field required"),
    ("[nodes.cam]\nkind = 3\n", "nodes.cam.kind: Input should be a valid string"),
    ('[nodes.cam]\nkind = "teleport"\n', "nodes.cam: unknown node kind 'teleport' (known: blobs, capture, echo"),
    (NODES + "fps = -1\n", "nodes.cam.fps: Input should be greater than or equal to 0"),
    (NODES + 'fps = "fast"\n', "nodes.cam.fps: Input should be a valid number"),
    (NODES + "colour = 1\n", "nodes.cam.colour: Extra inputs are not permitted"),
    (NODES + 'restart = "maybe"\n', "nodes.cam.restart: Input should be a valid boolean"),
    ('[nodes."cam 1"]\nkind = "echo"\n', "node name 'cam 1' is not a valid key name"),
    ('[nodes."a/b"]\nkind = "echo"\n', "node name 'a/b' is not a valid key name"),
    ('[bus]\nrig = "a/b"\n' + NODES, "bus.rig: Value error, rig 'a/b' is not a valid key name"),
    ('[bus]\nnamespace = "ar/*"\n' + NODES, "bus.namespace: Value error, namespace 'ar/*'"),
    ('[bus]\nmode = "router"\n' + NODES, "bus.mode: Input should be 'peer' or 'client'"),
    ('[bus]\nconnect = ["localhost:7447"]\n' + NODES, "bus.connect: Value error, endpoint 'localhost:7447'"),
    ("[bus]\nrouter_wait_s = -1\n" + NODES, "bus.router_wait_s: Input should be greater than or equal to 0"),
    ("[bus]\ncolour = 1\n" + NODES, "bus.colour: Extra inputs are not permitted"),
    ('bus = "demo"\n' + NODES, "bus: Input should be a valid dictionary"),
    ("[nodes.cam\nkind = 1\n", "not valid TOML"),
]


@pytest.mark.parametrize(("text", "expected"), FAULTS, ids=[expected for _, expected in FAULTS])
def test_pipeline_faults_name_the_field(tmp_path, text: str, expected: str):
    assert expected in pipeline_error(write(tmp_path, text))


def test_missing_pipeline_file_is_named(tmp_path):
    assert "cannot read" in pipeline_error(tmp_path / "absent.toml")


# --- bus settings from and to the environment ---

endpoints = st.builds("{}/{}:{}".format, st.sampled_from(["tcp", "udp", "quic"]),
                      st.sampled_from(["127.0.0.1", "[::1]", "router.lan"]), st.integers(0, 65535))
names = st.from_regex(r"[A-Za-z0-9_.\-]{1,10}", fullmatch=True)
bus_configs = st.builds(
    BusConfig,
    mode=st.sampled_from(["peer", "client"]),
    connect=st.lists(endpoints, max_size=3).map(tuple),
    listen=st.lists(endpoints, max_size=3).map(tuple),
    zenoh_config=st.none() | st.lists(names, min_size=1, max_size=3).map(lambda parts: Path("/", *parts)),
    namespace=st.lists(names, min_size=1, max_size=3).map("/".join),
    rig=names,
    autostart_router=st.booleans(),
    router_wait_s=st.floats(min_value=0, allow_nan=False),
)


@settings(max_examples=200, deadline=None)
@given(bus_configs)
def test_environment_carries_every_bus_setting(bus: BusConfig):
    env = bus.to_env()
    assert all(isinstance(v, str) for v in env.values())
    assert BusConfig.from_env(env) == bus


def test_empty_environment_gives_the_defaults():
    assert BusConfig.from_env({}) == BusConfig()
    assert BusConfig().uses_local_router


def test_environment_lists_are_comma_separated_and_trimmed():
    env = {"ARTRACK_CONNECT": " tcp/10.0.0.5:7447, ,tcp/10.0.0.6:7447,", "ARTRACK_MODE": "client"}
    bus = BusConfig.from_env(env)
    assert bus.connect == ("tcp/10.0.0.5:7447", "tcp/10.0.0.6:7447")
    assert bus.mode == "client"
    assert not bus.uses_local_router


@pytest.mark.parametrize(("value", "expected"), [("0", False), ("false", False), ("no", False), ("1", True)])
def test_router_autostart_from_environment(value: str, expected: bool):
    assert BusConfig.from_env({"ARTRACK_ROUTER_AUTOSTART": value}).autostart_router is expected


def test_overrides_win_over_the_environment_unless_unset():
    env = {"ARTRACK_RIG": "envrig", "ARTRACK_NAMESPACE": "envns", "ARTRACK_CONNECT": "tcp/a:1"}
    bus = BusConfig.from_env(env, rig="given", namespace=None, connect=())
    assert (bus.rig, bus.namespace, bus.connect) == ("given", "envns", ("tcp/a:1",))


@pytest.mark.parametrize(
    ("variable", "value", "field"),
    [
        ("ARTRACK_MODE", "router", "mode"),
        ("ARTRACK_RIG", "a/b", "rig"),
        ("ARTRACK_NAMESPACE", "ar/**", "namespace"),
        ("ARTRACK_CONNECT", "localhost:7447", "connect"),
        ("ARTRACK_LISTEN", "7447", "listen"),
        ("ARTRACK_ROUTER_WAIT_S", "-1", "router_wait_s"),
        ("ARTRACK_ROUTER_WAIT_S", "soon", "router_wait_s"),
    ],
)
def test_bad_environment_values_name_the_field(variable: str, value: str, field: str):
    with pytest.raises(ValidationError) as caught:
        BusConfig.from_env({variable: value})
    assert [error["loc"][0] for error in caught.value.errors()] == [field]
    assert value in str(caught.value)


def test_inputs_and_outputs_follow_from_the_kinds_and_sources_read_nothing(tmp_path):
    spec = read_pipeline(write(tmp_path, PIPELINE))
    assert (spec.nodes["cam"].inputs, spec.nodes["cam"].outputs) == ((), ("left/image", "left/camera_info",
                                                                         "left/truth"))
    assert (spec.nodes["relay"].inputs, spec.nodes["relay"].outputs) == (("left/image",), ("left/echo",))
    assert spec.sources() == ["cam"]


def test_stated_keys_that_disagree_with_the_parameters_are_refused_naming_both(tmp_path):
    path = write(tmp_path, PIPELINE + 'inputs = ["right/image"]\n')
    message = pipeline_error(path)
    assert "nodes.relay.inputs" in message and "['left/image']" in message and "['right/image']" in message
    assert read_pipeline(write(tmp_path, PIPELINE + 'inputs = ["left/image"]\n')).nodes["relay"].inputs == (
        "left/image",)


def test_a_saved_pipeline_reads_back_as_the_same_pipeline(tmp_path):
    from services.launcher.pipeline import save_pipeline, to_toml

    spec = read_pipeline(write(tmp_path, PIPELINE))
    saved = tmp_path / "saved.toml"
    save_pipeline(spec, saved, "made by a test\nsecond line")
    assert saved.read_text().startswith("# made by a test\n# second line\n\n")
    again = read_pipeline(saved)
    assert (again.bus, again.supervisor, list(again.nodes)) == (spec.bus, spec.supervisor, list(spec.nodes))
    assert to_toml(again) == to_toml(spec)
    assert "scene" not in saved.read_text()  # what was not given is not written
