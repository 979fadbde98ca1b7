"""Node parameters composed of option models: flat names, flat keys in and out, errors by flat name, and, for
every node kind found, the defaults a node runs are its algorithms' own."""

from __future__ import annotations

from typing import Annotated

import pytest
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from services.launcher.kinds import catalogue, kind
from services.runtime.params import Flat, NodeParams, flat_dump, flat_fields, flat_location, option_model


class Motion(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")

    max_gap_s: float = Field(default=0.2, gt=0, description="longest gap, s")
    acceleration: float = Field(default=5.0, ge=0, description="ignored acceleration, m/s^2")


class Matching(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")

    gate_rms: float = Field(default=0.001, gt=0, description="largest residual RMS, m")
    allow_missing: bool = Field(default=True, description="one sphere may hide")


class Following(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")

    gate: float = Field(default=0.015, gt=0, description="farthest from the prediction, m")
    motion: Motion = Motion()


class Sample(NodeParams):
    camera: str = "cam0"
    match: Annotated[Matching, Flat()] = Matching()
    tracking: Annotated[Following, Flat("predict_", names={"motion_max_gap_s": "predict_gap_s"},
                                        label="predict")] = Following()
    plain: Matching = Matching()


def test_nested_fields_go_by_their_declared_prefix_or_name():
    fields = flat_fields(Sample)
    assert list(fields) == ["camera", "gate_rms", "allow_missing", "predict_gate", "predict_gap_s",
                            "predict_motion_acceleration", "plain_gate_rms", "plain_allow_missing"]
    assert fields["predict_gap_s"].path == ("tracking", "motion", "max_gap_s")
    assert fields["predict_gap_s"].default == 0.2 and fields["predict_gap_s"].label == "predict"
    assert fields["predict_gap_s"].info.description == "longest gap, s"
    assert fields["gate_rms"].label == "" and fields["camera"].path == ("camera",)


def test_flat_keys_are_nested_and_dumped_flat_again():
    params = Sample.model_validate({"gate_rms": 0.002, "predict_gap_s": 0.5, "plain_allow_missing": False})
    assert params.match.gate_rms == 0.002 and params.tracking.motion.max_gap_s == 0.5
    assert params.plain.allow_missing is False and params.tracking.gate == 0.015
    assert flat_dump(params, exclude_unset=True) == {"gate_rms": 0.002, "predict_gap_s": 0.5,
                                                     "plain_allow_missing": False}
    assert Sample.model_validate(flat_dump(params)) == params
    assert Sample(**flat_dump(params, exclude_unset=True)) == params


def test_a_flat_key_wins_over_the_same_option_in_a_nested_value():
    params = Sample.model_validate({"match": Matching(gate_rms=0.003, allow_missing=False), "gate_rms": 0.004})
    assert params.match == Matching(gate_rms=0.004, allow_missing=False)
    assert Sample(match=Matching(gate_rms=0.005)).match.gate_rms == 0.005


def test_errors_name_the_flat_parameter():
    with pytest.raises(ValidationError) as caught:
        Sample.model_validate({"predict_gap_s": -1, "gate_rms": "wide", "bogus": 1})
    located = {problem["loc"]: problem["type"] for problem in caught.value.errors()}
    assert located == {("predict_gap_s",): "greater_than", ("gate_rms",): "float_parsing",
                       ("bogus",): "extra_forbidden"}
    assert flat_location(Sample, ("tracking", "motion", "max_gap_s")) == ("predict_gap_s",)
    assert flat_location(Sample, ("tracking",)) == ("tracking",)


def test_two_parameters_of_one_name_or_a_name_the_model_lacks_are_declaration_errors():
    class Twice(NodeParams):
        gate_rms: float = 1.0
        match: Annotated[Matching, Flat()] = Matching()

    class Unknown(NodeParams):
        match: Annotated[Matching, Flat(names={"gate": "g"})] = Matching()

    with pytest.raises(TypeError, match="parameter 'gate_rms' is both gate_rms and match.gate_rms"):
        flat_fields(Twice)
    with pytest.raises(TypeError, match="Flat names gate, which Matching does not have"):
        flat_fields(Unknown)


KINDS = sorted(catalogue().kinds)


@pytest.mark.parametrize("name", KINDS)
def test_a_node_runs_its_algorithms_default_options(name):
    """Each option model a node kind composes defaults to that model's own defaults: no drift between the
    node and the library; its flat names are unique; the model is frozen and refuses unknown fields."""
    params = kind(name).params
    flat_fields(params)
    for field, info in params.model_fields.items():
        options = option_model(info)
        if options is None:
            continue
        assert issubclass(params, NodeParams), f"{name}: {field} holds options, so Params takes flat keys"
        assert info.get_default(call_default_factory=True) == options(), f"{name}.{field} drifts from {options}"
        assert options.model_config.get("frozen") and options.model_config.get("extra") == "forbid"
        assert all(leaf.description for leaf in options.model_fields.values() if option_model(leaf) is None), \
            f"{options.__name__}: every option needs a description (its flag's help)"


def test_the_kinds_of_every_tracker_compose_option_models():
    composed = {name for name in KINDS if any(option_model(info) for info in kind(name).params.model_fields.values())}
    assert {"blobs", "rigid_bodies", "markers", "marker_pose", "keypoints", "features", "slam"} <= composed
