"""Flow plans from a pipeline's wiring, frame gaps, and the pace of a lossless capture."""

from __future__ import annotations

import dataclasses
import logging
import time
from pathlib import Path

import numpy as np
import pytest

from services.bus.stats import SeqGaps
from services.calibration.rig import Rig, write_rig
from services.detection.blobs import measure_kernel, merged_kernel
from services.estimation.bodies import kernels
from services.launcher import kernels as launcher_kernels
from services.launcher.flow import FlowSettings, lossless
from services.launcher.job import JobFile, build_job
from services.launcher.layout import SINGLE, laid_out
from services.launcher.pipeline import NodeSpec, PipelineError, PipelineSpec, preflight, read_pipeline, to_toml
from services.launcher.tracker import Tracker
from services.runtime import compiled
from services.synthetic import make_scene


def job(tracker: str, options: dict | None = None, **source) -> PipelineSpec:
    """The job of ``artrack run TRACKER`` on a capture of ``source`` with ``options`` ({field: value})."""
    chosen = Tracker.load(tracker)
    return build_job(chosen, NodeSpec(kind="capture", **source), options or {}, chosen.flags({}), Path("run.mcap"),
                     JobFile(Path("run.rrd")))


def test_a_finite_source_runs_lossless_and_waits_for_every_node_that_takes_its_images():
    plans = job("marker", source=["synthetic:markers"], frames=10).flow_plans()
    assert plans["capture"].lossless and sorted(plans["capture"].credits_from) == ["marker-cam0", "recorder", "viewer"]
    assert all(plans[name].acks for name in ("marker-cam0", "recorder", "viewer"))
    assert plans["marker-cam0"].upstream == ("capture",)
    assert sorted(plans["recorder"].upstream) == ["capture", "marker-cam0"]
    assert plans["capture"].upstream == ()


def test_a_foxglove_file_is_written_by_a_node_that_takes_every_frame_and_waits_for_every_end(tmp_path):
    chosen = Tracker.load("marker")
    out = tmp_path / "live.mcap"
    source = NodeSpec(kind="capture", source=["synthetic:markers"], frames=10)
    spec = build_job(chosen, source, {"marker_length": 0.05}, chosen.flags({}), tmp_path / "run.mcap",
                     foxglove=JobFile(out))
    assert spec.nodes["foxglove"].params == {"serve": False, "mcap": str(out)}
    plans = spec.flow_plans()
    assert "foxglove" in plans["capture"].credits_from and plans["foxglove"].acks
    assert sorted(plans["foxglove"].upstream) == ["capture", "marker-cam0"]
    assert laid_out(spec, "single").groups()[SINGLE] == ("capture", "marker-cam0")  # the sinks apart
    preflight(spec, "job")
    out.write_bytes(b"kept")
    with pytest.raises(PipelineError, match=r"job: nodes.foxglove: .*live.mcap exists: give --force"):
        preflight(spec, "job")
    forced = build_job(chosen, source, {"marker_length": 0.05}, chosen.flags({}), foxglove=JobFile(out, True))
    preflight(forced, "job")


def test_a_rerun_file_that_exists_is_refused_before_the_job_unless_forced(tmp_path):
    chosen = Tracker.load("marker")
    out = tmp_path / "run.rrd"
    source = NodeSpec(kind="capture", source=["synthetic:markers"], frames=10)
    out.write_bytes(b"kept")
    kept = build_job(chosen, source, {"marker_length": 0.05}, chosen.flags({}), rerun=JobFile(out))
    with pytest.raises(PipelineError, match=r"job: nodes.viewer: .*run.rrd exists: give --force"):
        preflight(kept, "job")
    forced = build_job(chosen, source, {"marker_length": 0.05}, chosen.flags({}), rerun=JobFile(out, True))
    assert forced.nodes["viewer"].params == {"rrd": str(out), "force": True}
    preflight(forced, "job")
    assert out.read_bytes() == b"kept"


def test_nodes_fed_by_results_wait_for_ends_but_give_no_credits():
    plans = job("stereo", source=["synthetic:ir_rig"], frames=10).flow_plans()
    takers = set(plans["capture"].credits_from)
    assert {"blobs-cam0", "blobs-cam1", "recorder", "viewer"} <= takers and "bodies" not in takers
    assert not plans["bodies"].acks and {"blobs-cam0", "blobs-cam1"} <= set(plans["bodies"].upstream)


@pytest.mark.parametrize("source", [{"source": ["synthetic:markers"]}, {"source": ["camera:0"]},
                                    {"source": ["synthetic:markers"], "frames": 5, "loop": True}])
def test_endless_sources_stay_real_time_unless_asked(source):
    spec = job("marker", **source)
    assert not spec.lossless() and not spec.flow_plans()["capture"].credits_from
    forced = spec.model_copy(update={"flow": FlowSettings(mode="lossless", window=2)})
    assert forced.lossless() and forced.flow_plans()["capture"].window == 2


def test_realtime_asked_for_a_finite_source_takes_no_credits():
    spec = job("marker", source=["synthetic:markers"], frames=10)
    realtime = spec.model_copy(update={"flow": FlowSettings(mode="realtime")})
    assert not realtime.lossless() and not any(plan.acks for plan in realtime.flow_plans().values())
    assert not lossless(FlowSettings(), {})


def test_the_flow_table_round_trips_through_a_pipeline_file_and_is_checked(tmp_path):
    spec = job("marker", source=["synthetic:markers"], frames=10).model_copy(
        update={"flow": FlowSettings(mode="realtime", window=8)})
    text = to_toml(spec)
    assert "[flow]" in text and 'mode = "realtime"' in text and "window = 8" in text
    path = tmp_path / "job.toml"
    path.write_text(text)
    assert read_pipeline(path).flow == FlowSettings(mode="realtime", window=8)
    path.write_text('[flow]\nmode = "fast"\n\n[nodes.cam]\nkind = "capture"\n')
    with pytest.raises(PipelineError, match="flow.mode"):
        read_pipeline(path)


def test_gaps_count_the_frames_skipped_and_start_over_when_a_source_does():
    gaps = SeqGaps()
    assert [gaps.note("a", seq) for seq in (0, 1, 4, 5, 9)] == [0, 0, 2, 0, 3]
    assert gaps.note("a", 2) == 0 and gaps.note("a", 3) == 0  # started over: no gap counted
    assert gaps.note("b", 7) == 0  # the first frame seen on a key
    assert gaps.tail(10) == (10 - 3) + (10 - 7)


def test_the_stereo_job_s_preflight_prepares_each_kind_s_compiled_kernels_once_and_says_so_when_it_compiles(
        monkeypatch, caplog):
    """Two blobs nodes and a bodies node: each kind's kernels prepared once; only a slow one is said compiling."""
    calls: list[str] = []
    monkeypatch.setattr(compiled, "LOADED_S", 0.05)
    spec = job("stereo", source=["synthetic:ir_rig"], frames=10)
    assert sorted(node.kind for node in spec.nodes.values()).count("blobs") == 2
    monkeypatch.setattr(kernels, "warm", lambda: calls.append("bodies"))
    monkeypatch.setattr(measure_kernel, "warm", lambda: calls.append("blobs"))
    monkeypatch.setattr(merged_kernel, "warm", lambda: calls.append("merged blobs"))
    with caplog.at_level(logging.INFO, logger=compiled.__name__):
        preflight(spec, "job")
    assert sorted(calls) == ["blobs", "bodies", "merged blobs"] and "compiling" not in caplog.text  # loaded: quiet
    monkeypatch.setattr(kernels, "warm", lambda: (time.sleep(0.3), calls.append("bodies")))
    with caplog.at_level(logging.INFO, logger=compiled.__name__):
        preflight(spec, "job")
    assert sorted(calls) == ["blobs", "blobs", "bodies", "bodies", "merged blobs", "merged blobs"]
    assert "compiling the rigid bodies node's kernels" in caplog.text and "blobs" not in caplog.text


def test_a_job_refused_for_a_rig_made_at_another_frame_size_compiles_nothing(monkeypatch, tmp_path):
    """The calibrations are held against the frames before any kernel is loaded or compiled: a wrong file is
    told at once, not after a minute of compiling."""
    calls: list[str] = []
    monkeypatch.setattr(kernels, "warm", lambda: calls.append("bodies"))
    monkeypatch.setattr(measure_kernel, "warm", lambda: calls.append("blobs"))
    monkeypatch.setattr(merged_kernel, "warm", lambda: calls.append("merged blobs"))
    rig = tmp_path / "rig.yaml"
    doubled = np.diag([2.0, 2.0, 1.0])
    write_rig(rig, Rig("bar", tuple(dataclasses.replace(camera, width=2 * camera.width, height=2 * camera.height,
                                                        K=doubled @ camera.K)
                                    for camera in make_scene("ir_rig").cameras)))
    spec = job("stereo", {"rig_file": str(rig)}, source=["synthetic:ir_rig"], frames=10)
    with pytest.raises(PipelineError, match="camera cam0 is calibrated for 1280x960, its frames are 640x480"):
        preflight(spec, "job")
    assert calls == []


def test_every_kind_s_compiled_code_is_built_by_one_command(monkeypatch):
    calls: list[str] = []
    monkeypatch.setattr(kernels, "warm", lambda: calls.append("bodies"))
    monkeypatch.setattr(measure_kernel, "warm", lambda: calls.append("blobs"))
    monkeypatch.setattr(merged_kernel, "warm", lambda: calls.append("merged blobs"))
    assert launcher_kernels.prepare_all() == ["blobs", "rigid_bodies"]
    assert calls == ["blobs", "merged blobs", "bodies"]


def test_a_stereo_job_on_a_missing_folder_names_the_folder_not_the_cameras_it_would_have_had(tmp_path):
    """The stereo tracker needs two cameras; a folder that does not exist has none to tell, and is what is wrong."""
    with pytest.raises(PipelineError, match=rf"^job: nodes.capture: images:{tmp_path}/none: no such folder$"):
        job("stereo", source=[f"images:{tmp_path / 'none'}"])
