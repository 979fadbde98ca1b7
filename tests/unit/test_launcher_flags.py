"""Flags generated from parameter models, and tracker templates filled from them."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Annotated, Any, ClassVar, Literal

import pytest
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from services.launcher.flags import add_flags, explain, flags_for, given_values, type_name
from services.launcher.kinds import DiscoveryError, catalogue, kind, search_roots
from services.launcher.pipeline import PipelineError, PipelineSpec, read_pipeline, to_toml
from services.launcher.tracker import Tracker
from services.runtime.params import Flat, NodeParams


class Sample(BaseModel):
    model_config = ConfigDict(extra="forbid")
    FLAGS: ClassVar[dict[str, str]] = {"wait_s": "wait"}

    rate: float = Field(default=1.0, gt=0, description="how fast")
    count: int = 0
    loop: bool = False
    names: tuple[str, ...] = ()
    where: Path | None = None
    mode: Literal["fast", "slow"] = "fast"
    lengths: dict[int, float] = Field(default_factory=dict)
    extra: dict[str, Any] = Field(default_factory=dict)
    wait_s: float = 2.0


def parse(argv: list[str], skip: frozenset[str] = frozenset()) -> tuple[dict[str, Any], list]:
    parser = argparse.ArgumentParser(exit_on_error=False)
    flags = flags_for(Sample, skip)
    add_flags(parser.add_argument_group("sample"), flags)
    return given_values(parser.parse_args(argv), flags), flags


def test_each_field_is_a_flag_and_only_given_ones_are_set():
    values, flags = parse(["--rate", "2.5", "--loop", "--names", "a", "b", "--names", "c", "--mode", "slow"])
    assert {f.option for f in flags} >= {"--rate", "--count", "--loop", "--names", "--where", "--wait"}
    assert values == {"rate": "2.5", "loop": True, "names": ["a", "b", "c"], "mode": "slow"}
    model = Sample.model_validate(values)
    assert (model.rate, model.loop, model.names, model.mode) == (2.5, True, ("a", "b", "c"), "slow")


def test_values_are_converted_by_the_field_type_not_by_their_look():
    values, _ = parse(["--count", "7", "--where", "12", "--lengths", "3=0.05", "--extra", 'name="x"',
                       "--extra", "n=4", "--no-loop"])
    model = Sample.model_validate(values)
    assert model.count == 7 and model.where == Path("12") and model.loop is False
    assert model.lengths == {3: 0.05}
    assert model.extra == {"name": "x", "n": 4}


def test_an_untyped_dict_value_must_be_json():
    with pytest.raises(ValueError, match="--extra 'name=x': VALUE must be JSON"):
        parse(["--extra", "name=x"])


def test_a_refused_value_is_named_by_its_flag():
    values, flags = parse(["--rate", "-1", "--wait", "soon"])
    with pytest.raises(ValidationError) as caught:
        Sample.model_validate(values)
    text = explain(caught.value, flags, "sample")
    assert "--rate: Input should be greater than 0" in text
    assert "--wait: Input should be a valid number" in text


def test_skipped_fields_get_no_flag():
    _, flags = parse([], frozenset({"rate", "names"}))
    assert {"--rate", "--names"}.isdisjoint(f.option for f in flags)


class Gates(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")

    gate_rms: float = Field(default=0.001, gt=0, description="largest residual RMS, m")
    bridge: int = 1


class Composed(NodeParams):
    rate: float = 1.0
    match: Annotated[Gates, Flat(names={"bridge": "match_bridge"}, label="match")] = Gates()
    follow: Annotated[Gates, Flat("follow_", names={"bridge": "bridge"})] = Gates()


def test_nested_option_models_give_prefixed_flags_with_their_description_and_default():
    parser = argparse.ArgumentParser(exit_on_error=False)
    flags = flags_for(Composed)
    add_flags(parser.add_argument_group("composed"), flags)
    assert [f.option for f in flags] == ["--rate", "--gate-rms", "--match-bridge", "--follow-gate-rms", "--bridge"]
    assert "match: largest residual RMS, m (float; default 0.001)" in " ".join(parser.format_help().split())
    values = given_values(parser.parse_args(["--follow-gate-rms", "0.01", "--bridge", "2"]), flags)
    assert values == {"follow_gate_rms": "0.01", "bridge": "2"}
    model = Composed.model_validate(values)
    assert (model.follow, model.match) == (Gates(gate_rms=0.01, bridge=2), Gates())
    with pytest.raises(ValidationError) as caught:
        Composed.model_validate({"follow_gate_rms": "-1"})
    assert explain(caught.value, flags, "composed") == "--follow-gate-rms: Input should be greater than 0"


def test_the_stereo_trackers_flags_set_its_nodes_option_models_and_save_as_flat_keys(tmp_path):
    stereo = Tracker.load("stereo")
    flags = stereo.flags({})
    nodes = stereo.expand(["cam0", "cam1"], {"gate_rms": "0.002", "predict_gap_s": "0.5", "min_sigma": "2"}, flags)
    assert nodes["bodies"].params == {"cameras": ["cam0", "cam1"], "gate_rms": "0.002", "predict_gap_s": "0.5"}
    bodies = kind("rigid_bodies").validate(nodes["bodies"].params)
    assert bodies.match.gate_rms == 0.002 and bodies.tracking.motion.max_gap_s == 0.5  # type: ignore[attr-defined]
    assert kind("blobs").validate(nodes["blobs-cam1"].params).log.min_sigma == 2.0  # type: ignore[attr-defined]
    path = tmp_path / "stereo.toml"
    path.write_text(to_toml(PipelineSpec(nodes=nodes)))
    assert 'gate_rms = 0.002\npredict_gap_s = 0.5' in path.read_text()
    assert read_pipeline(path).nodes["bodies"].params == {"cameras": ["cam0", "cam1"], "gate_rms": 0.002,
                                                          "predict_gap_s": 0.5}
    with pytest.raises(ValueError, match="--predict-gap-s: Input should be greater than 0"):
        stereo.expand(["cam0", "cam1"], {"predict_gap_s": "0"}, flags)


@pytest.mark.parametrize(("annotation", "expected"), [(float, "float"), (Path | None, "path"),
                                                      (tuple[int, ...], "list of int"),
                                                      (dict[int, float], "int -> float"),
                                                      (dict[str, Any], "str -> JSON"),
                                                      (Literal["a", "b"], "choice"),
                                                      (float | Literal["auto"], "float or 'auto'"),
                                                      (int | str, "int or str")])
def test_type_names_for_help(annotation, expected):
    assert type_name(annotation) == expected


def test_the_built_in_kinds_and_trackers_are_found_where_they_are_declared():
    found = catalogue()
    assert found.kinds["marker_pose"] == "services.estimation.markers.node"
    assert found.kinds["capture"] == "services.capture.node"
    assert found.trackers["marker"].parent.parent.name == "estimation"
    assert kind("echo").keys(kind("echo").validate({"camera": "cam3"})) == (("cam3/image",), ("cam3/echo",))


def test_an_unknown_kind_lists_the_known_ones():
    with pytest.raises(ValueError, match=r"unknown node kind 'teleport' \(known: .*marker_pose"):
        kind("teleport")


def test_a_plugin_root_that_is_not_a_package_is_refused():
    assert search_roots({"ARTRACK_PLUGINS": " a, b ,"}) == ("services", "a", "b")
    with pytest.raises(DiscoveryError, match="ARTRACK_PLUGINS: 'json.decoder' is not an importable package"):
        catalogue(("services", "json.decoder"))


def test_a_tracker_expands_per_camera_and_applies_the_options_to_every_node_having_the_field():
    marker = Tracker.load("marker")
    flags = marker.flags({})
    nodes = marker.expand(["left", "right"], {"marker_length": "0.05", "depth": "3"}, flags)
    assert set(nodes) == {"marker-left", "marker-right"}
    assert nodes["marker-right"].kind == "marker_pose"
    assert nodes["marker-right"].params == {"camera": "right", "marker_length": "0.05", "depth": "3"}


def test_a_field_of_another_type_than_the_sources_gets_the_kinds_prefix():
    source = {f.field: f for f in flags_for(kind("capture").params)}
    options = {f.option for f in Tracker.load("marker").flags(source)}
    assert "--marker-pose-calib" in options and "--calib" not in options


def test_a_bad_option_for_a_template_node_names_the_flag():
    marker = Tracker.load("marker")
    with pytest.raises(ValueError, match="--method: Input should be 'lm', 'ippe' or 'ippe\\+lm' \\(given 'best'\\)"):
        marker.expand(["cam0"], {"method": "best"}, marker.flags({}))


def test_a_template_without_kinds_is_refused(tmp_path, monkeypatch):
    broken = tmp_path / "trackers" / "broken.toml"
    broken.parent.mkdir()
    broken.write_text('[nodes.a]\ncamera = "x"\n')
    monkeypatch.setattr("services.launcher.tracker.catalogue", lambda: type("C", (), {"trackers": {"broken": broken}}))
    with pytest.raises(PipelineError, match="each \\[nodes.NAME\\] table needs a kind"):
        Tracker.load("broken")


def test_artrack_version_names_the_installed_release(capsys):
    from importlib import metadata

    from services.cli import main

    with pytest.raises(SystemExit) as done:
        main(["--version"])
    assert done.value.code == 0
    assert capsys.readouterr().out.strip() == f"artrack {metadata.version('artrack')}"


def test_artrack_run_help_lists_the_trackers_and_succeeds_while_no_tracker_is_an_error(capsys):
    from services.cli import main

    assert main(["run", "--help"]) == 0
    listed = capsys.readouterr().out
    assert "marker" in listed and "echo" in listed and "artrack run TRACKER --help" in listed
    assert main(["run"]) == 2
