"""Restart budget, ``[supervisor]`` validation, live parameter changes, reload planning and JSON log lines."""

from __future__ import annotations

import json
import logging
import threading
from pathlib import Path

import pytest

from protocol.message import Header
from protocol.system import ConfigChange, PipelineHealth, SupervisedNode
from services.bus.session import BusConfig
from services.capture.node import Params as CaptureParams
from services.detection.markers.node import Params as MarkerParams
from services.launcher import daemon
from services.launcher.pipeline import PipelineError, params_model, read_pipeline
from services.launcher.reload import plan_reload
from services.launcher.status import Status
from services.launcher.supervisor import RestartBudget
from services.runtime.logs import JsonFormatter, NodeTag, log_format
from services.runtime.reconfig import LiveParams, Refused, changed_params

PIPELINE = """
[nodes.cam]
kind = "capture"
fps = {fps}
scene = {{ width = 64, height = 64 }}

[nodes.markers]
kind = "markers"
{markers}
"""


def _spec(tmp_path: Path, markers: str = "", extra: str = "", name: str = "p.toml", fps: float = 10):
    path = tmp_path / name
    path.write_text(extra + PIPELINE.format(markers=markers, fps=fps))
    return read_pipeline(path)


def test_budget_allows_max_restarts_per_window_then_refuses():
    budget = RestartBudget(max_restarts=2, window_s=10.0)
    assert [budget.allow(t) for t in (0.0, 1.0, 2.0)] == [True, True, False]
    assert budget.allow(10.5) is True  # the restart at 0.0 has left the window
    assert budget.allow(10.6) is False  # 1.0 and 10.5 are still in it
    assert RestartBudget(max_restarts=0, window_s=1.0).allow(0.0) is False


@pytest.mark.parametrize(("table", "expected"), [
    ("max_restarts = -1", "supervisor.max_restarts: Input should be greater than or equal to 0"),
    ("window_s = 0", "supervisor.window_s: Input should be greater than 0"),
    ("backoff_s = 5\nmax_backoff_s = 1", "max_backoff_s (1.0) is below backoff_s (5.0)"),
    ("restarts = 3", "supervisor.restarts: Extra inputs are not permitted"),
])
def test_bad_supervisor_table_names_field_and_reason(tmp_path, table, expected):
    with pytest.raises(PipelineError) as caught:
        _spec(tmp_path, extra=f"[supervisor]\n{table}\n")
    assert expected in str(caught.value) and str(tmp_path / "p.toml") in str(caught.value)


def test_supervisor_table_is_read(tmp_path):
    spec = _spec(tmp_path, extra="[supervisor]\nmax_restarts = 2\nwindow_s = 30\n")
    assert (spec.supervisor.max_restarts, spec.supervisor.window_s, spec.supervisor.backoff_s) == (2, 30.0, 0.5)


def test_changed_params_applies_reloadable_fields_only():
    params = CaptureParams(fps=10, frames=5)
    assert changed_params(params, {"fps": 30}).fps == 30
    assert changed_params(params, {"fps": 30}).frames == 5
    with pytest.raises(Refused) as caught:
        changed_params(params, {"fps": 30, "frames": 1, "bogus": 2})
    assert caught.value.reasons == {"frames": "not reloadable: needs a restart", "bogus": "no such parameter"}
    with pytest.raises(Refused) as caught:
        changed_params(params, {"fps": -1})
    assert list(caught.value.reasons) == ["fps"] and "greater than or equal to 0" in caught.value.reasons["fps"]


def test_live_params_answer_is_all_or_nothing_and_apply_may_refuse():
    built = []

    def apply(new: MarkerParams) -> None:
        built.append(new.detection.detector())  # a bad aruco parameter raises ValueError here

    live = LiveParams(MarkerParams(marker_length=0.05), apply)
    change = ConfigChange(header=Header(stamp_ns=1), values={"parameters": '{"minMarkerPerimeterRate": 0.2}'})
    answer = live.answer("markers", change)
    assert answer.applied == change.values and answer.refused == {} and len(built) == 1
    detection = live.value.detection
    assert detection.parameters == {"minMarkerPerimeterRate": 0.2} and detection.marker_length == 0.05
    assert json.loads(answer.params["parameters"]) == {"minMarkerPerimeterRate": 0.2}

    bad = live.answer("markers", ConfigChange(header=Header(stamp_ns=2), values={"parameters": '{"noSuch": 1}'}))
    assert bad.applied == {} and "noSuch" in bad.refused["parameters"]
    assert live.value.detection.parameters == {"minMarkerPerimeterRate": 0.2}, "a refused change must leave the params"
    mixed = live.answer("markers", ConfigChange(header=Header(stamp_ns=3),
                                                values={"marker_length": "0.1", "camera": '"cam1"'}))
    assert mixed.refused == {"camera": "not reloadable: needs a restart"} and live.value.detection.marker_length == 0.05
    typed = live.answer("markers", ConfigChange(header=Header(stamp_ns=5), values={"marker_length": '"0.07"'}))
    assert typed.applied == {"marker_length": "0.07"}, "applied as the node holds it: a number, not the text typed"
    not_json = live.answer("markers", ConfigChange(header=Header(stamp_ns=4), values={"marker_length": "0,1"}))
    assert "not JSON" in not_json.refused["marker_length"]


def test_values_given_as_text_are_converted_by_the_fields_types():
    live = LiveParams(MarkerParams(marker_length=0.05))
    text = {"marker_length": "0.06", "refinement": "subpix", "lengths": '{"3": 0.1}',
            "parameters": '{"minMarkerPerimeterRate": 0.05}'}
    answer = live.answer("m", ConfigChange(header=Header(stamp_ns=1),
                                           values={k: json.dumps(v) for k, v in text.items()}))
    assert answer.refused == {}, answer.refused
    detection = live.value.detection
    assert (detection.marker_length, detection.refinement) == (0.06, "subpix")
    assert (detection.lengths, detection.parameters) == ({3: 0.1}, {"minMarkerPerimeterRate": 0.05})
    bad = live.answer("m", ConfigChange(header=Header(stamp_ns=1), values={"lengths": json.dumps("{3: x")}))
    assert "lengths" in bad.refused and "not JSON" in bad.refused["lengths"]


def test_plan_reload_yields_live_changes(tmp_path):
    running = _spec(tmp_path, markers='camera = "cam0"')
    wanted = _spec(tmp_path, markers='camera = "cam0"\nmarker_length = 0.1', name="q.toml", fps=25)
    plan = plan_reload(running, wanted, params_model)
    assert plan.refused == [] and plan.changes == {"cam": {"fps": 25}, "markers": {"marker_length": 0.1}}


def test_plan_reload_refuses_what_needs_a_restart_naming_node_and_field(tmp_path):
    running = _spec(tmp_path, markers='camera = "cam0"\nmarker_length = 0.1')
    wanted = _spec(tmp_path, markers='camera = "cam1"', extra="[supervisor]\nmax_restarts = 9\n", name="q.toml")
    plan = plan_reload(running, wanted, params_model)
    assert plan.changes == {}
    assert "[supervisor] changed: needs a restart of `artrack up`" in plan.refused
    assert "node markers: field camera is not reloadable (markers): needs a restart" in plan.refused
    assert not any("marker_length" in reason for reason in plan.refused)  # dropped -> back to default: reloadable

    for field, value in (("nice", 5), ("cpus", (0,))):
        moved = running.model_copy(update={"nodes": {**running.nodes, "cam": running.nodes["cam"].model_copy(
            update={field: value})}})
        assert plan_reload(running, moved, params_model).refused == \
            [f"node cam: {field} changed: needs a restart of `artrack up`"]

    more = wanted.model_copy(update={"nodes": {"cam": wanted.nodes["cam"], "echo": wanted.nodes["cam"]}})
    reasons = plan_reload(running, more, params_model).refused
    assert "node echo: new node: needs a restart of `artrack up`" in reasons
    assert "node markers: removed: needs a restart of `artrack up`" in reasons


def test_json_log_lines_carry_the_fields_and_extras():
    record = logging.LogRecord("artrack.up", logging.WARNING, __file__, 1, "echo died %d times", (3,), None)
    record.child = "echo"
    NodeTag("cam").filter(record)
    entry = json.loads(JsonFormatter().format(record))
    assert entry["level"] == "warning" and entry["logger"] == "artrack.up" and entry["node"] == "cam"
    assert entry["message"] == "echo died 3 times" and entry["child"] == "echo"
    assert entry["time"].endswith("+00:00")


def test_a_group_tags_each_line_with_the_node_whose_thread_logs_it():
    tag = NodeTag("cam0", frozenset({"capture", "blobs-cam0"}))
    tagged: dict[str, str] = {}

    def log_on_thread() -> None:
        record = logging.LogRecord("artrack.blobs", logging.INFO, __file__, 1, "up", (), None)
        tag.filter(record)
        tagged[threading.current_thread().name] = record.node

    for name in ("blobs-cam0", "elsewhere"):
        thread = threading.Thread(target=log_on_thread, name=name)
        thread.start()
        thread.join()
    assert tagged == {"blobs-cam0": "blobs-cam0", "elsewhere": "cam0"}


def test_log_format_comes_from_flag_then_environment(monkeypatch):
    monkeypatch.setenv("ARTRACK_LOG_FORMAT", "json")
    assert (log_format(), log_format("text")) == ("json", "text")
    monkeypatch.setenv("ARTRACK_LOG_FORMAT", "xml")
    with pytest.raises(ValueError, match="'xml'.*ARTRACK_LOG_FORMAT.*text, json"):
        log_format()


def test_a_health_check_here_ignores_other_hosts_pipelines():
    def health(host: str, state: str) -> PipelineHealth:
        return PipelineHealth(header=Header(stamp_ns=1), pipeline=f"{host}.toml", host=host, pid=1, uptime_s=1.0,
                              nodes=(SupervisedNode(name=f"{host}-cam", kind="capture", state=state),))

    status = Status({"a": health("box-a", "running"), "b": health("box-b", "failed")})
    assert status.problems() == ["node box-b-cam is failed"]
    assert status.on_host("box-a").problems() == []
    assert status.on_host("box-b").problems() == ["node box-b-cam is failed"]
    assert status.on_host("box-c").problems() == ["no `artrack up` or `artrack run` answered on this rig"]


class _RefusingSession:
    """A session that opens but refuses the health queryable."""

    def __init__(self) -> None:
        self.closed = False

    def declare_queryable(self, key: str, handler: object) -> None:
        raise RuntimeError("queryable refused")

    def close(self) -> None:
        self.closed = True


def test_leaving_closes_a_session_whose_health_queryable_was_refused(tmp_path, monkeypatch):
    session = _RefusingSession()
    monkeypatch.setattr(daemon, "open_session", lambda bus: session)
    pipeline = daemon.Daemon(tmp_path / "p.toml", _spec(tmp_path), BusConfig())
    with pytest.raises(RuntimeError, match="queryable refused"):
        pipeline._join()
    pipeline._leave()
    assert session.closed
