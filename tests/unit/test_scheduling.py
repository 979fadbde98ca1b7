"""The priority and CPUs a pipeline's nodes ask for their processes: files, flags, checks and what a child gets."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from services.bus.session import BusConfig
from services.launcher import scheduling
from services.launcher.layout import laid_out, scheduled
from services.launcher.pipeline import PipelineError, preflight, processes, read_pipeline, to_toml
from services.launcher.scheduling import Scheduling, check_scheduling, may_raise_priority, parse_cpus, parse_nice

PIPELINE = """
[nodes.cam]
kind = "capture"
source = ["synthetic:markers"]
process = "rig"
nice = 5

[nodes.relay]
kind = "echo"
camera = "cam0"
process = "rig"
nice = 2
cpus = [0]

[nodes.rec]
kind = "recorder"
out = "{out}"
"""


def spec_of(tmp_path: Path, text: str = PIPELINE):
    path = tmp_path / "pipeline.toml"
    path.write_text(text.format(out=tmp_path / "run.mcap"))
    return read_pipeline(path)


def test_a_process_takes_the_most_urgent_nice_of_its_nodes_and_their_cpus(tmp_path):
    spec = spec_of(tmp_path)
    assert spec.scheduling("rig") == Scheduling(2, (0,))
    assert spec.scheduling("rec") == Scheduling()
    by_name = {p.name: p.scheduling for p in processes(spec, BusConfig())}
    assert by_name == {"rig": Scheduling(2, (0,)), "rec": Scheduling()}


def test_a_file_with_nice_and_cpus_is_written_back_as_it_was_read(tmp_path):
    spec = spec_of(tmp_path)
    again = spec_of(tmp_path, to_toml(spec).replace("{", "{{").replace("}", "}}"))
    assert {n: (node.nice, node.cpus) for n, node in again.nodes.items()} == \
        {"cam": (5, None), "relay": (2, (0,)), "rec": (None, None)}


@pytest.mark.parametrize(("line", "why"), [
    ("nice = 20", "nodes.relay.nice: Input should be less than or equal to 19"),
    ("nice = -21", "nodes.relay.nice: Input should be greater than or equal to -20"),
    ("cpus = []", "give one or more different CPU numbers, 0 or more, got []"),
    ("cpus = [-1]", "got [-1]"),
    ("cpus = [1, 1]", "got [1, 1]"),
])
def test_a_node_asking_for_what_no_process_can_have_is_refused_naming_the_field(tmp_path, line, why):
    text = PIPELINE.replace("nice = 2\ncpus = [0]", line)
    with pytest.raises(PipelineError) as caught:
        spec_of(tmp_path, text)
    assert str(caught.value).startswith(str(tmp_path / "pipeline.toml")) and why in str(caught.value)


def test_the_nodes_of_one_process_may_not_name_different_cpus(tmp_path):
    with pytest.raises(PipelineError, match=r"nodes\.relay\.cpus \[0\]: node cam of the same process asks for \[1\]"):
        spec_of(tmp_path, PIPELINE.replace("nice = 5", "nice = 5\ncpus = [1]"))


def test_flags_without_a_node_leave_the_sinks_alone_and_a_node_named_is_set_alone(tmp_path):
    spec = scheduled(spec_of(tmp_path), ["7", "relay=-3"], ["0-1"])
    assert {n: (node.nice, node.cpus) for n, node in spec.nodes.items()} == \
        {"cam": (7, (0, 1)), "relay": (-3, (0, 1)), "rec": (None, None)}
    moved = scheduled(laid_out(spec_of(tmp_path), "separate"), [], ["cam=1", "relay=0"])
    assert (moved.scheduling("cam"), moved.scheduling("relay")) == (Scheduling(5, (1,)), Scheduling(2, (0,)))


@pytest.mark.parametrize(("nice", "cpus", "why"), [
    (["x"], [], r"--nice 'x': give \[NODE=\]N, N a whole number from -20 to 19"),
    (["cam=20"], [], r"--nice 'cam=20': nice must be from -20 \(most urgent\) to 19, got 20"),
    (["camera=1"], [], r"--nice 'camera=1': no node 'camera' \(nodes: cam, relay, rec\)"),
    ([], ["0-x"], r"--cpus '0-x': give \[NODE=\]LIST, LIST CPU numbers and ranges such as 0,2-3"),
    ([], ["cam=1"], r"--cpus: nodes\.relay\.cpus \[0\]: node cam of the same process asks for \[1\]"),
])
def test_flags_that_cannot_be_taken_are_refused_naming_the_flag(tmp_path, nice, cpus, why):
    with pytest.raises(PipelineError, match=why):
        scheduled(spec_of(tmp_path), nice, cpus)


def test_cpu_lists_and_nice_values_parse_as_written():
    assert parse_cpus("3,0-1,1") == (0, 1, 3)
    assert (parse_nice("-20"), parse_nice("19")) == (-20, 19)
    assert parse_cpus("2-4") == (2, 3, 4)
    for text in ("", "-1", "2-", "a", "1,", "4-2", "0,4-2"):
        with pytest.raises(ValueError):
            parse_cpus(text)


def test_cpus_this_process_may_not_use_are_refused_before_anything_starts(tmp_path):
    outside = max(os.sched_getaffinity(0)) + 1
    spec = scheduled(spec_of(tmp_path), [], [f"rec={outside}"])
    allowed = ", ".join(map(str, sorted(os.sched_getaffinity(0))))
    with pytest.raises(PipelineError, match=rf"^job: nodes\.rec\.cpus \[{outside}\]: this machine lets artrack run on "
                                            rf"CPUs {allowed} only$"):
        preflight(spec, "job")


def test_a_priority_above_this_processs_is_refused_when_it_may_not_be_given(monkeypatch):
    own = os.getpriority(os.PRIO_PROCESS, 0)
    monkeypatch.setattr(scheduling, "may_raise_priority", lambda nice: False)
    with pytest.raises(ValueError, match=rf"nodes\.bodies\.nice {own - 1}: a priority above this process's \(nice "
                                         rf"{own}\) needs the CAP_SYS_NICE capability"):
        check_scheduling({"bodies": Scheduling(own - 1, None)})
    check_scheduling({"bodies": Scheduling(min(own + 1, 19), None)})


def test_the_probe_leaves_this_process_as_it_was_and_lowering_is_always_allowed():
    own = os.getpriority(os.PRIO_PROCESS, 0)
    assert may_raise_priority(19)
    may_raise_priority(-5)
    assert os.getpriority(os.PRIO_PROCESS, 0) == own
